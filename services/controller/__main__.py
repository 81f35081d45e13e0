"""`python -m ra2vipas.services.controller`: run a rig's controller (as `ra2vipas controller`)."""

from __future__ import annotations

import os

from ra2vipas.services.transport import service


def main(argv: list[str] | None = None) -> None:
    p = service.parser("python -m ra2vipas.services.controller",
                       "Run a rig's controller: measurements in, pan commands out, for the pointing policies it serves "
                       "(--policy; default every installed one), which it announces on rig/{rig}/policies.")
    p.add_argument("--rig", default=os.environ.get("RA2VIPAS_RIG", "rig-1"), help="Rig name [env RA2VIPAS_RIG; default rig-1].")
    p.add_argument("--beta", type=float, default=4.0, help="UCB exploration weight beta (>= 0; default 4).")
    p.add_argument("--policy", "-p", action="append", metavar="NAME",
                   help="A pointing policy this controller serves: an installed name or module:Class (repeatable or "
                        "comma-separated) [env RA2VIPAS_POLICY; default: every installed policy].")
    service.add_realtime_priority(p)
    args = service.parse(p, argv)
    if args.beta < 0:
        p.error(f"Invalid value for '--beta': {args.beta:g} is not in the range x>=0")
    from ra2vipas.services.controller import registry
    from ra2vipas.services.controller.node import ControllerNode, served_policies
    from ra2vipas.services.controller.policy import ControllerSettings
    from ra2vipas.services.protocol.keys import check_chunk
    from ra2vipas.services.transport.runtime import configure_logging

    configure_logging(args.log_level)
    service.check_name(args.rig, check_chunk)
    given = args.policy or ([os.environ["RA2VIPAS_POLICY"]] if os.environ.get("RA2VIPAS_POLICY") else [])
    names = [n.strip() for value in given for n in value.replace(" ", ",").split(",") if n.strip()]
    try:
        served = list(served_policies(names or None).values())
    except registry.UnknownPolicy as err:
        raise service.ServiceError(str(err), service.EXIT_USAGE) from None
    service.claim_cpu()
    service.run_node(f"controller[{args.rig}]", service.zenoh_of(args),
                     lambda bus: ControllerNode(bus, args.rig, ControllerSettings(beta=args.beta), policies=served,
                                                realtime_priority=args.realtime_priority))


if __name__ == "__main__":
    service.main(main)
