"""`python -m ra2vipas.services.learner`: run the POD learner (as `ra2vipas learner`)."""

from __future__ import annotations

import os

from ra2vipas.services.transport import service


def main(argv: list[str] | None = None) -> None:
    p = service.parser("python -m ra2vipas.services.learner",
                       "Run the POD learner: trains p_hat_D(r) once per scenario and seed, serves it.")
    p.add_argument("--name", default=os.environ.get("RA2VIPAS_LEARNER_NAME", "learner"),
                   help="Instance name [env RA2VIPAS_LEARNER_NAME; default learner].")
    p.add_argument("--cache-dir", default=os.environ.get("RA2VIPAS_MODEL_CACHE"),
                   help="Keep trained POD models here across restarts [env RA2VIPAS_MODEL_CACHE].")
    args = service.parse(p, argv)
    from ra2vipas.services.learner.node import LearnerNode
    from ra2vipas.services.protocol.keys import check_chunk
    from ra2vipas.services.transport.runtime import configure_logging

    configure_logging(args.log_level)
    service.check_name(args.name, check_chunk, "learner name")
    service.yield_cpu()
    service.run_node(f"learner[{args.name}]", service.zenoh_of(args), lambda bus: LearnerNode(bus, args.name, args.cache_dir))


if __name__ == "__main__":
    service.main(main)
