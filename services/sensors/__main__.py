"""`python -m ra2vipas.services.sensors`: run a rig's simulated sensors (as `ra2vipas sensors`)."""

from __future__ import annotations

import os

from ra2vipas.services.transport import service


def main(argv: list[str] | None = None) -> None:
    p = service.parser("python -m ra2vipas.services.sensors",
                       "Run a rig's simulated sensors: the world, the camera detector, Rx(iso) and Rx(dir).")
    p.add_argument("--rig", default=os.environ.get("RA2VIPAS_RIG", "rig-1"), help="Rig name [env RA2VIPAS_RIG; default rig-1].")
    p.add_argument("--hardware", action="append", metavar="NAME=VALUE",
                   help="Pin a hardware parameter of this simulated rig (repeatable): frames_per_rf, rf_period_s, "
                        "fov_half_angle_deg, box_bearing_noise_deg, antenna_model, antenna_curvature, antenna_floor_db.")
    p.add_argument("--undescribed", action="store_true", help="Serve no rig descriptor (behave as a v1 node).")
    service.add_realtime_priority(p)
    args = service.parse(p, argv)
    from ra2vipas.services.protocol.keys import check_chunk
    from ra2vipas.services.protocol.scenario import ScenarioError, parse_value
    from ra2vipas.services.sensors.node import SensorsNode, pinned_descriptor
    from ra2vipas.services.transport.runtime import configure_logging

    configure_logging(args.log_level)
    service.check_name(args.rig, check_chunk)
    values = {}
    try:
        for item in args.hardware or []:
            name, sep, text = item.partition("=")
            if not sep or not name.strip():
                raise ValueError(f"--hardware expects NAME=VALUE, got {item!r}")
            name = name.strip()
            values[name] = text.strip() if name == "antenna_model" else parse_value(name, text)
        descriptor = pinned_descriptor(args.rig, values)
    except (ValueError, ScenarioError) as err:
        raise service.ServiceError(str(err), service.EXIT_USAGE) from None
    service.claim_cpu()
    service.run_node(f"sensors[{args.rig}]", service.zenoh_of(args),
                     lambda bus: SensorsNode(bus, args.rig, descriptor=descriptor, describe=not args.undescribed,
                                             realtime_priority=args.realtime_priority))


if __name__ == "__main__":
    service.main(main)
