"""Every Zenoh key expression of ra2vipas, one builder per key family.

All keys live under ``ra2vipas/v1/<plane>/...``. Planes never share a prefix, so a wildcard
on one plane cannot catch another plane's traffic (``tests/protocol`` checks it):

========  =============================================================================
plane     what travels there
========  =============================================================================
data      what a real platform produces and consumes: pan commands, step measurements,
          the POD training stream
control   orchestration: episode start/stop sent to a rig
result    the controller's per-episode trace (estimates, pans), for scoring; the sensors'
          timing; what a node rejected
truth     the simulator's ground truth, for scoring only; never read by a controller or
          a learner
model     the learner's queryable serving the POD model
rig       what each rig says about itself: its sensors' ``RigDescriptor`` and its controller's
          ``ControllerInfo`` (the policies it serves), two queryables
alive     liveliness tokens: who is up
========  =============================================================================

A *rig* is one sensing platform (sensors node) with its controller; ``rig`` is a single
key chunk such as ``rig-1`` (letters, digits, ``-`` and ``_``).
"""

from __future__ import annotations

import re

PREFIX = "ra2vipas/v1"

PLANES = ("data", "control", "result", "truth", "model", "rig", "alive")

_CHUNK = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def check_chunk(name: str, what: str = "rig") -> str:
    """``name`` if it is a valid single key chunk (no ``/``, ``*``, ``$``, ``?``, ``#``)."""
    if not _CHUNK.match(name):
        raise ValueError(f"{what} {name!r} must be 1-64 letters, digits, '-' or '_'")
    return name


# -- data plane --------------------------------------------------------------------------------

def command(rig: str) -> str:
    """Pan command s_{t+1} for one rig. Payload ``Command``. Controller publishes; sensors subscribe."""
    return f"{PREFIX}/data/{check_chunk(rig)}/command"


def measurement(rig: str) -> str:
    """Step measurement z_t (RSSI pair + nu frames of box bearings). Payload ``Measurement``.
    Sensors publish; the rig's controller subscribes."""
    return f"{PREFIX}/data/{check_chunk(rig)}/measurement"


def training(rig: str) -> str:
    """Queryable of a rig's sensors that runs a POD training episode and replies with its stream.
    Query payload ``TrainingRequest``; reply ``TrainingStream``. The learner queries."""
    return f"{PREFIX}/data/{check_chunk(rig)}/training"


def training_any() -> str:
    """What the learner queries to reach any rig able to run a training episode."""
    return f"{PREFIX}/data/*/training"


# -- control plane -----------------------------------------------------------------------------

def episode_control(rig: str) -> str:
    """Episode start/stop for one rig. Payload ``EpisodeStart`` or ``EpisodeStop``.
    The orchestrator publishes; the rig's sensors and controller subscribe."""
    return f"{PREFIX}/control/{check_chunk(rig)}/episode"


def episode_control_all() -> str:
    """Every rig's episode control key: what the orchestrator may publish on (access control)."""
    return f"{PREFIX}/control/*/episode"


# -- result plane ------------------------------------------------------------------------------

def episode_result(rig: str) -> str:
    """The controller's trace of a finished (or failed) episode. Payload ``EpisodeResult``.
    The controller publishes; the orchestrator subscribes (``episode_result_all``)."""
    return f"{PREFIX}/result/{check_chunk(rig)}/episode"


def episode_result_all() -> str:
    return f"{PREFIX}/result/*/episode"


def episode_timing(rig: str) -> str:
    """Sample-to-command latencies of a realtime episode, measured by the sensors node.
    Payload ``EpisodeTiming``. Sensors publish; the orchestrator subscribes."""
    return f"{PREFIX}/result/{check_chunk(rig)}/timing"


def episode_timing_all() -> str:
    return f"{PREFIX}/result/*/timing"


def episode_rejected(rig: str) -> str:
    """A rig's node rejected a message of an episode (protocol 1.1): payload ``ErrorReply`` with
    the ``episode_id`` and the node's reason (e.g. a field it does not know). The rig's sensors
    and controller publish; the orchestrator subscribes (``episode_rejected_all``) and fails
    that attempt at once, naming the reason."""
    return f"{PREFIX}/result/{check_chunk(rig)}/rejected"


def episode_rejected_all() -> str:
    return f"{PREFIX}/result/*/rejected"


# -- truth plane -------------------------------------------------------------------------------

def episode_truth(rig: str) -> str:
    """Ground truth of a simulated episode (target bearings, the Tx index). Payload
    ``EpisodeTruth``. A *simulated* sensors node publishes; only the orchestrator subscribes."""
    return f"{PREFIX}/truth/{check_chunk(rig)}/episode"


def episode_truth_all() -> str:
    return f"{PREFIX}/truth/*/episode"


def training_truth(rig: str) -> str:
    """Queryable of a *simulated* rig's sensors: the ground truth of the training episode of
    (scenario, seed) (true RSSI and POD per sample), to score the learner's R^2. Query payload
    ``TrainingRequest``, reply ``TrainingTruth``. Only the orchestrator queries
    (``training_truth_any``)."""
    return f"{PREFIX}/truth/{check_chunk(rig)}/training"


def training_truth_any() -> str:
    return f"{PREFIX}/truth/*/training"


# -- model plane -------------------------------------------------------------------------------

def pod_model() -> str:
    """Queryable of the learner: query payload ``PODRequest``, reply ``PODResponse`` (the model
    for that scenario and seed, trained once and cached). Controllers and the orchestrator query."""
    return f"{PREFIX}/model/pod"


# -- rig plane ---------------------------------------------------------------------------------

def rig_info(rig: str) -> str:
    """Queryable of a rig's sensors: what the rig is (``RigDescriptor``: kind, nu, T_RF, half-FoV,
    box noise, Rx(dir) response, ...). Any query payload (empty is fine); reply ``RigDescriptor``.
    The rig's controller and the orchestrator query it. A v1 sensors node serves none: the rig is
    then *undescribed* and its controller models it from the campaign's scenario."""
    return f"{PREFIX}/rig/{check_chunk(rig)}/info"


def rig_info_any() -> str:
    """Every rig's descriptor queryable (what the orchestrator may query)."""
    return f"{PREFIX}/rig/*/info"


def rig_policies(rig: str) -> str:
    """Queryable of a rig's controller (protocol 1.2): the pointing policies it serves
    (``ControllerInfo``: each policy's name, package and version, and the protocol the
    controller speaks). Any query payload (empty is fine). The orchestrator queries it when
    the controller's liveliness token appears and hands that rig only episodes of those
    policies. A 1.0 or 1.1 controller serves none: it serves the four built-ins."""
    return f"{PREFIX}/rig/{check_chunk(rig)}/policies"


def rig_policies_any() -> str:
    """Every rig's controller-info queryable (what the orchestrator may query)."""
    return f"{PREFIX}/rig/*/policies"


# -- liveliness --------------------------------------------------------------------------------

ROLES = ("sensors", "controller", "learner", "orchestrator")


def alive(role: str, name: str) -> str:
    """Liveliness token of one process: ``role`` in ROLES, ``name`` the rig (sensors,
    controller) or an instance name (learner, orchestrator)."""
    if role not in ROLES:
        raise ValueError(f"role must be one of {ROLES}")
    return f"{PREFIX}/alive/{role}/{check_chunk(name, 'name')}"


def alive_all() -> str:
    return f"{PREFIX}/alive/**"


def every_key() -> str:
    """Every key of every plane. Never subscribed to: access control uses it to let any node
    learn where subscribers and queryables are (``services/transport/acl.py``)."""
    return f"{PREFIX}/**"


def parse_alive(key: str) -> tuple[str, str] | None:
    """(role, name) of a liveliness key, or None if it is not one."""
    parts = str(key).split("/")
    if len(parts) == 5 and "/".join(parts[:3]) == f"{PREFIX}/alive" and parts[3] in ROLES:
        return parts[3], parts[4]
    return None


def rig_of(key: str) -> str | None:
    """The rig chunk of a data/control/result/truth/rig key, or None."""
    parts = str(key).split("/")
    if len(parts) >= 4 and "/".join(parts[:2]) == PREFIX and parts[2] in ("data", "control", "result", "truth", "rig"):
        return parts[3]
    return None
