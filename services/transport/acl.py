"""Who may do what on which key: the Zenoh access control of a secured ra2vipas deployment.

A pure module (no zenoh import): it turns the deployment's *identities* (one per process
role, and per rig) into the ``access_control`` object of a Zenoh 1.x router configuration
(eclipse-zenoh ``DEFAULT_CONFIG.json5``: ``rules``, ``subjects``, ``policies``). The router
enforces it on every session it serves, so every service must join as a *client* of that
router: the router sees, and filters, everything.

The default is *deny*: an identity may only do what its role is granted below, and a user
the policy does not name may do nothing. Zenoh checks two flows on each session:

* **ingress**, what the identity sends: its puts, the subscribers, queryables and liveliness
  tokens it declares, its queries and replies;
* **egress**, what the router delivers to it: the puts it receives, the queries its
  queryables receive, the replies to its queries, the liveliness tokens it is told about.

A rule allows a message when one of its key expressions *includes* the message's key
expression, so a wildcard subscription (``result/*/episode``) needs a rule that includes
that wildcard, and a rig's rules, which name only its own keys, can never subscribe to
another rig's traffic.

Per role (``{rig}`` the identity's rig, ``{name}`` its instance name; keys from
``ra2vipas.services.protocol.keys``):

=============  ===============================================================================
role           may
=============  ===============================================================================
sensors        put ``data/{rig}/measurement``, ``truth/{rig}/episode`` (a *simulated* sensor
               knows the truth), ``result/{rig}/timing`` and ``result/{rig}/rejected``;
               subscribe to its rig's
               ``control`` and ``data/{rig}/command``; serve ``data/{rig}/training``,
               ``truth/{rig}/training`` and ``rig/{rig}/info`` (its descriptor); hold the
               token ``alive/sensors/{rig}``
controller     put ``data/{rig}/command``, ``result/{rig}/episode`` and ``result/{rig}/rejected``;
               subscribe to its
               rig's ``control`` and ``data/{rig}/measurement``; query ``model/pod`` and
               ``rig/{rig}/info``; serve ``rig/{rig}/policies`` (the policies it serves);
               hold ``alive/controller/{rig}``
rig            both of the above for one rig (``ra2vipas rig``: one process, two sessions)
learner        serve ``model/pod``; query ``data/*/training``; hold ``alive/learner/{name}``
orchestrator   put ``control/*/episode``; subscribe to ``result/*/…`` and
               ``truth/*/episode``; query ``model/pod``, ``truth/*/training``,
               ``rig/*/info`` and ``rig/*/policies``; watch
               ``alive/**``; hold ``alive/orchestrator/{name}``
operator       put ``truth/*/episode`` and serve ``truth/*/training`` (ground truth entered
               for real rigs); nothing else
=============  ===============================================================================

Every identity may also *learn where* subscribers and queryables are (egress declarations
on ``ra2vipas/v1/**``): a publisher needs it to send at all, and it reveals no payload.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from ra2vipas.services.protocol import keys

ROLES = ("orchestrator", "learner", "sensors", "controller", "rig", "operator")
RIG_ROLES = ("sensors", "controller", "rig")
MATCHES = ("username", "certificate", "both")

INGRESS, EGRESS = "ingress", "egress"
PUT, DELETE = "put", "delete"
SUBSCRIBE, QUERYABLE = "declare_subscriber", "declare_queryable"
QUERY, REPLY = "query", "reply"
TOKEN, LIVELINESS_QUERY, LIVELINESS_SUBSCRIBER = "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"
MESSAGES = (PUT, DELETE, SUBSCRIBE, QUERY, REPLY, QUERYABLE, TOKEN, LIVELINESS_QUERY, LIVELINESS_SUBSCRIBER)

_USER = re.compile(r"^[A-Za-z0-9_.-]{1,80}$")


class AclError(ValueError):
    """An identity or a policy is invalid; the message says which."""


@dataclass(frozen=True)
class Grant:
    """``messages`` allowed in ``flow`` on keys included in ``key_exprs``."""

    flow: str
    messages: tuple[str, ...]
    key_exprs: tuple[str, ...]


@dataclass(frozen=True)
class Identity:
    """One set of credentials: ``user`` is the user name it authenticates with (and the
    common name of its TLS certificate), ``role`` one of ROLES, ``name`` the rig (sensors,
    controller, rig) or the instance name (learner, orchestrator) it may announce."""

    user: str
    role: str
    name: str

    def __post_init__(self) -> None:
        if not _USER.match(self.user):
            raise AclError(f"identity {self.user!r}: a user name is 1-80 letters, digits, '.', '-' or '_'")
        if self.role not in ROLES:
            raise AclError(f"identity {self.user!r}: role must be one of {', '.join(ROLES)}, got {self.role!r}")
        try:
            keys.check_chunk(self.name, "rig" if self.role in RIG_ROLES else "name")
        except ValueError as err:
            raise AclError(f"identity {self.user!r}: {err}") from None


def standard_identities(rigs: list[str], split_rigs: list[str] = (), operators: list[str] = (),
                        learner: str = "learner", orchestrator: str = "orchestrator") -> list[Identity]:
    """The identities of a deployment: the orchestrator, the learner, one ``rig`` identity
    per rig in ``rigs`` (user = the rig's name, for ``ra2vipas rig``), a ``sensors`` and a
    ``controller`` identity per rig in ``split_rigs`` (users ``{rig}.sensors``,
    ``{rig}.controller``: a rig whose two halves run apart) and an ``operator`` per name."""
    out = [Identity(orchestrator, "orchestrator", orchestrator), Identity(learner, "learner", learner)]
    out += [Identity(rig, "rig", rig) for rig in rigs]
    for rig in split_rigs:
        out += [Identity(f"{rig}.sensors", "sensors", rig), Identity(f"{rig}.controller", "controller", rig)]
    out += [Identity(op, "operator", op) for op in operators]
    users = [i.user for i in out]
    duplicates = sorted({u for u in users if users.count(u) > 1})
    if duplicates:
        raise AclError(f"identity names must be unique: {', '.join(duplicates)} given twice")
    rig_names = [*rigs, *split_rigs]
    if len(set(rig_names)) != len(rig_names):
        raise AclError("a rig is either whole (--rigs) or split (--split-rigs), and named once")
    return out


def _sensors(rig: str) -> list[Grant]:
    return [
        Grant(INGRESS, (PUT,), (keys.measurement(rig), keys.episode_truth(rig), keys.episode_timing(rig), keys.episode_rejected(rig))),
        Grant(INGRESS, (SUBSCRIBE,), (keys.episode_control(rig), keys.command(rig))),
        Grant(EGRESS, (PUT,), (keys.episode_control(rig), keys.command(rig))),
        Grant(INGRESS, (QUERYABLE, REPLY), (keys.training(rig), keys.training_truth(rig), keys.rig_info(rig))),
        # queries reach a queryable with the querier's key expression: the learner's wildcard
        Grant(EGRESS, (QUERY,), (keys.training(rig), keys.training_any(), keys.training_truth(rig), keys.training_truth_any(),
                                 keys.rig_info(rig), keys.rig_info_any())),
        Grant(INGRESS, (TOKEN,), (keys.alive("sensors", rig),)),
    ]


def _controller(rig: str) -> list[Grant]:
    return [
        Grant(INGRESS, (PUT,), (keys.command(rig), keys.episode_result(rig), keys.episode_rejected(rig))),
        Grant(INGRESS, (SUBSCRIBE,), (keys.episode_control(rig), keys.measurement(rig))),
        Grant(EGRESS, (PUT,), (keys.episode_control(rig), keys.measurement(rig))),
        Grant(INGRESS, (QUERY,), (keys.pod_model(), keys.rig_info(rig))),
        Grant(EGRESS, (REPLY,), (keys.pod_model(), keys.rig_info(rig))),
        Grant(INGRESS, (QUERYABLE, REPLY), (keys.rig_policies(rig),)),
        # the orchestrator's query reaches the queryable with its wildcard
        Grant(EGRESS, (QUERY,), (keys.rig_policies(rig), keys.rig_policies_any())),
        Grant(INGRESS, (TOKEN,), (keys.alive("controller", rig),)),
        # it watches its own rig's sensors (a node whose token went and came back may be another: ``node._on_descriptor``)
        Grant(INGRESS, (LIVELINESS_SUBSCRIBER, LIVELINESS_QUERY), (keys.alive("sensors", rig),)),
        Grant(EGRESS, (TOKEN,), (keys.alive("sensors", rig),)),
    ]


def _learner(name: str) -> list[Grant]:
    return [
        Grant(INGRESS, (QUERYABLE, REPLY), (keys.pod_model(),)),
        Grant(EGRESS, (QUERY,), (keys.pod_model(),)),
        Grant(INGRESS, (QUERY,), (keys.training_any(),)),
        Grant(EGRESS, (REPLY,), (keys.training_any(),)),
        Grant(INGRESS, (TOKEN,), (keys.alive("learner", name),)),
    ]


def _orchestrator(name: str) -> list[Grant]:
    observed = (keys.episode_result_all(), keys.episode_timing_all(), keys.episode_rejected_all(), keys.episode_truth_all())
    return [
        Grant(INGRESS, (PUT,), (keys.episode_control_all(),)),
        Grant(INGRESS, (SUBSCRIBE,), observed),
        Grant(EGRESS, (PUT,), observed),
        Grant(INGRESS, (QUERY,), (keys.pod_model(), keys.training_truth_any(), keys.rig_info_any(), keys.rig_policies_any())),
        Grant(EGRESS, (REPLY,), (keys.pod_model(), keys.training_truth_any(), keys.rig_info_any(), keys.rig_policies_any())),
        Grant(INGRESS, (LIVELINESS_SUBSCRIBER, LIVELINESS_QUERY), (keys.alive_all(),)),
        Grant(EGRESS, (TOKEN,), (keys.alive_all(),)),
        Grant(INGRESS, (TOKEN,), (keys.alive("orchestrator", name),)),
    ]


def _operator() -> list[Grant]:
    return [
        Grant(INGRESS, (PUT,), (keys.episode_truth_all(),)),
        Grant(INGRESS, (QUERYABLE, REPLY), (keys.training_truth_any(),)),
        Grant(EGRESS, (QUERY,), (keys.training_truth_any(),)),
    ]


DISCOVERY = Grant(EGRESS, (SUBSCRIBE, QUERYABLE), (keys.every_key(),))


def grants(identity: Identity) -> list[Grant]:
    """Everything ``identity`` may do (see the module's table)."""
    role, name = identity.role, identity.name
    if role == "sensors":
        out = _sensors(name)
    elif role == "controller":
        out = _controller(name)
    elif role == "rig":
        out = _sensors(name) + _controller(name)
    elif role == "learner":
        out = _learner(name)
    elif role == "orchestrator":
        out = _orchestrator(name)
    else:
        out = _operator()
    return [*out, DISCOVERY]


def access_control(identities: list[Identity], match: str = "username") -> dict:
    """Zenoh's ``access_control`` configuration object for ``identities``: default deny, one
    subject per identity (by user name, by certificate common name, or both must match),
    one allow rule per grant.

    Raises ``AclError`` for an empty or duplicated identity list or an unknown ``match``."""
    if match not in MATCHES:
        raise AclError(f"match must be one of {', '.join(MATCHES)}, got {match!r}")
    if not identities:
        raise AclError("an access control policy needs at least one identity")
    users = [i.user for i in identities]
    if len(set(users)) != len(users):
        raise AclError("identity user names must be unique")
    rules, subjects, policies = [], [], []
    for identity in identities:
        subject: dict = {"id": identity.user}
        if match in ("username", "both"):
            subject["usernames"] = [identity.user]
        if match in ("certificate", "both"):
            subject["cert_common_names"] = [identity.user]
        subjects.append(subject)
        rule_ids = []
        for n, grant in enumerate(grants(identity)):
            rule_id = f"{identity.user}/{n}"
            rules.append({"id": rule_id, "permission": "allow", "flows": [grant.flow], "messages": list(grant.messages),
                          "key_exprs": list(grant.key_exprs)})
            rule_ids.append(rule_id)
        policies.append({"id": identity.user, "rules": rule_ids, "subjects": [identity.user]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}

