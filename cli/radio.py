"""``ra2vipas radio``: real radio data for the simulator (issue 20; docs/radio.md).

``radio import`` turns BLE recordings in the Position-Annotated BLE RSSI Dataset's format
(``.mbd`` lines ``timestamp,receiver,beacon,rssi``, one file per receiver and beacon position
``<receiver>_<x>_<y>_<z>.mbd``) and the receivers' positions into a channel file the
``recorded`` radio reads (``services/sensors/channel_file.py``)."""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import Annotated, Optional

import typer

from ra2vipas.cli.output import EXIT_USAGE, fail

app = typer.Typer(help="Real radio data: import BLE recordings as a channel for the recorded radio.", no_args_is_help=True)


@app.command("import")
def import_(
    recordings: Annotated[list[Path], typer.Argument(metavar="MBD_OR_DIR...", help="The .mbd files, or folders of them.")],
    devices: Annotated[Path, typer.Option("--devices", metavar="FILE", help="The receivers' positions: the dataset's tetam.dev "
                                          "(Dongles:{mac: [[x, y, z], colour, name]}) or a CSV name,x,y,z[,mac].")],
    output: Annotated[Path, typer.Option("--output", "-o", metavar="FILE", help="The channel file to write (.npz); name it "
                                         "<name>.npz in a folder of $RA2VIPAS_CHANNELS and set radio_channel=<name>.")],
    receivers: Annotated[Optional[list[str]], typer.Option("--receiver", metavar="NAME", help="Keep this receiver only "
                                                           "(repeatable; default: all).")] = None,
    seconds: Annotated[Optional[float], typer.Option(min=1.0, help="Keep the first SECONDS of each recording (default: all).")] = None,
    max_range: Annotated[Optional[float], typer.Option("--max-range", min=0.1, metavar="M", help="Keep the beacon positions within "
                                                       "M metres of their receiver (default: all).")] = None,
    source: Annotated[str, typer.Option(help="Where the recordings come from (stored in the file).")] = "",
    licence: Annotated[str, typer.Option(help="Their licence (stored in the file).")] = "",
) -> None:
    """Write a channel file from .mbd recordings; a malformed line is reported with its file and
    line number, and nothing is written."""
    from ra2vipas.services.sensors.channel_file import ChannelFileError, import_recordings, save

    files: list[Path] = []
    for item in recordings:
        if item.is_dir():
            files += sorted(item.glob("*.mbd"))
        elif item.is_file():
            files.append(item)
        else:
            fail(f"no such file or folder: {item}", EXIT_USAGE)
    if not files:
        fail("no .mbd recording given", EXIT_USAGE)
    command = "ra2vipas radio import " + " ".join(
        [shlex.quote(str(p)) for p in recordings] + ["--devices", shlex.quote(str(devices))]
        + [f"--receiver {shlex.quote(r)}" for r in receivers or []] + ([f"--seconds {seconds:g}"] if seconds else [])
        + ([f"--max-range {max_range:g}"] if max_range else []) + ["-o", shlex.quote(str(output))])
    try:
        channel = import_recordings(files, devices, output, receivers=receivers, seconds=seconds, max_range_m=max_range,
                                    command=command)
        if source or licence:
            save(channel, output, {"source": source, "licence": licence})
    except ChannelFileError as err:
        fail(str(err))
    fit = channel.meta["fit"]
    print(f"wrote {output}: {len(channel.rec_receiver)} recordings of {len(channel.receivers)} receivers, {len(channel.rssi)} packets; "
          + (f"fit kappa {fit['kappa_dbm']} dBm, exponent {fit['exponent']}" if fit else "no log-distance fit (one distance)"))
