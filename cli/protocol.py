"""``ra2vipas protocol schemas OUTDIR``: the wire messages' JSON Schemas for third-party nodes."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from ra2vipas.cli.output import fail

app = typer.Typer(help="The wire protocol (key expressions and message schemas).", no_args_is_help=True)


def schema_documents() -> dict[str, dict]:
    """File name -> JSON Schema of every wire message."""
    from ra2vipas.services.protocol.messages import WIRE_MESSAGES, episode_control_adapter

    docs = {f"{m.__name__}.json": m.model_json_schema() for m in WIRE_MESSAGES}
    docs["EpisodeControl.json"] = episode_control_adapter.json_schema()
    return docs


@app.command("schemas")
def schemas(outdir: Annotated[Path, typer.Argument(help="Directory to write one <Message>.json per message into.")]) -> None:
    """Write the JSON Schema of every wire message into OUTDIR."""
    try:
        outdir.mkdir(parents=True, exist_ok=True)
        for name, doc in sorted(schema_documents().items()):
            (outdir / name).write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")
    except OSError as err:
        fail(f"cannot write schemas to {outdir}: {err.strerror or err}")
    print(f"wrote {len(schema_documents())} schemas to {outdir}")
