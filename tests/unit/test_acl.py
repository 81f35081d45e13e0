"""The access control builder (services/transport/acl.py): what each identity may do, decided
the way Zenoh's router decides it (a rule's key expression must include the message's)."""

from __future__ import annotations

import json

import pytest
import zenoh

from ra2vipas.services.protocol import keys
from ra2vipas.services.transport.acl import (
    EGRESS,
    INGRESS,
    LIVELINESS_SUBSCRIBER,
    MESSAGES,
    PUT,
    QUERY,
    QUERYABLE,
    REPLY,
    SUBSCRIBE,
    TOKEN,
    AclError,
    Identity,
    access_control,
    grants,
    standard_identities,
)


def allowed(policy: dict, user: str, flow: str, message: str, key: str) -> bool:
    """Zenoh's decision (zenoh/src/net/routing/interceptor/authorization.rs) on ``policy`` for
    a session authenticated as ``user``: default deny; allowed when a rule of a policy of a
    subject naming the user has the flow and message and a key expression including ``key``."""
    assert policy["enabled"] and policy["default_permission"] == "deny"
    subjects = {s["id"] for s in policy["subjects"] if user in s.get("usernames", [user])}
    rules = {r["id"]: r for r in policy["rules"]}
    for p in policy["policies"]:
        if subjects & set(p["subjects"]):
            for rid in p["rules"]:
                r = rules[rid]
                if (r["permission"] == "allow" and flow in r["flows"] and message in r["messages"]
                        and any(zenoh.KeyExpr(k).includes(zenoh.KeyExpr(key)) for k in r["key_exprs"])):
                    return True
    return False


IDENTITIES = standard_identities(["rig-1", "rig-2"], split_rigs=["robot-1"], operators=["lab"])
POLICY = access_control(IDENTITIES)


def test_standard_identities_name_every_role():
    assert [(i.user, i.role, i.name) for i in IDENTITIES] == [
        ("orchestrator", "orchestrator", "orchestrator"), ("learner", "learner", "learner"), ("rig-1", "rig", "rig-1"),
        ("rig-2", "rig", "rig-2"), ("robot-1.sensors", "sensors", "robot-1"), ("robot-1.controller", "controller", "robot-1"),
        ("lab", "operator", "lab")]


def test_the_policy_is_a_zenoh_access_control_object():
    assert set(POLICY) == {"enabled", "default_permission", "rules", "subjects", "policies"}
    assert {s["id"] for s in POLICY["subjects"]} == {i.user for i in IDENTITIES}
    for rule in POLICY["rules"]:
        assert rule["permission"] == "allow" and set(rule["flows"]) <= {INGRESS, EGRESS} and set(rule["messages"]) <= set(MESSAGES)
        for k in rule["key_exprs"]:
            assert k.startswith(f"{keys.PREFIX}/")
            zenoh.KeyExpr(k)
    assert len({r["id"] for r in POLICY["rules"]}) == len(POLICY["rules"])
    conf = zenoh.Config()
    conf.insert_json5("access_control", json.dumps(POLICY))  # the keys are Zenoh's
    both = access_control(IDENTITIES, match="both")
    assert all(s["usernames"] == s["cert_common_names"] == [s["id"]] for s in both["subjects"])
    assert all(list(s) == ["id", "cert_common_names"] for s in access_control(IDENTITIES, match="certificate")["subjects"])


# (who, flow, message, key) that the policy must allow: a rig's own work
LEGIT = [
    ("rig-1", INGRESS, PUT, keys.measurement("rig-1")),
    ("rig-1", INGRESS, PUT, keys.command("rig-1")),
    ("rig-1", INGRESS, PUT, keys.episode_result("rig-1")),
    ("rig-1", INGRESS, PUT, keys.episode_truth("rig-1")),
    ("rig-1", INGRESS, SUBSCRIBE, keys.episode_control("rig-1")),
    ("rig-1", EGRESS, PUT, keys.episode_control("rig-1")),
    ("rig-1", INGRESS, QUERYABLE, keys.training("rig-1")),
    ("rig-1", EGRESS, QUERY, keys.training_any()),
    ("rig-1", INGRESS, TOKEN, keys.alive("sensors", "rig-1")),
    ("rig-1", INGRESS, TOKEN, keys.alive("controller", "rig-1")),
    ("robot-1.sensors", INGRESS, PUT, keys.measurement("robot-1")),
    ("robot-1.controller", INGRESS, PUT, keys.episode_result("robot-1")),
    ("robot-1.controller", INGRESS, LIVELINESS_SUBSCRIBER, keys.alive("sensors", "robot-1")),  # its rig's sensors come and go
    ("robot-1.controller", EGRESS, TOKEN, keys.alive("sensors", "robot-1")),
    ("learner", INGRESS, QUERY, keys.training_any()),
    ("learner", INGRESS, QUERYABLE, keys.pod_model()),
    ("orchestrator", INGRESS, PUT, keys.episode_control("rig-2")),
    ("orchestrator", INGRESS, SUBSCRIBE, keys.episode_result_all()),
    ("orchestrator", INGRESS, LIVELINESS_SUBSCRIBER, keys.alive_all()),
    ("orchestrator", EGRESS, TOKEN, keys.alive("sensors", "rig-2")),
    ("lab", INGRESS, PUT, keys.episode_truth("robot-1")),
]

# what issue 14's probes did as an authenticated rig, and more: all denied
FORBIDDEN = [
    ("rig-1", INGRESS, PUT, keys.measurement("rig-2")),
    ("rig-1", INGRESS, PUT, keys.command("rig-2")),
    ("rig-1", INGRESS, PUT, keys.episode_result("rig-2")),
    ("rig-1", INGRESS, PUT, keys.episode_result("evil")),
    ("rig-1", INGRESS, PUT, keys.episode_truth("rig-2")),
    ("rig-1", INGRESS, PUT, keys.episode_control("rig-1")),
    ("rig-1", INGRESS, PUT, keys.episode_control("rig-2")),
    ("rig-1", INGRESS, SUBSCRIBE, keys.episode_control("rig-2")),
    ("rig-1", INGRESS, SUBSCRIBE, keys.episode_result_all()),
    ("rig-1", INGRESS, SUBSCRIBE, f"{keys.PREFIX}/data/*/measurement"),
    ("rig-1", INGRESS, SUBSCRIBE, keys.every_key()),
    ("rig-1", EGRESS, PUT, keys.measurement("rig-2")),
    ("rig-1", EGRESS, PUT, keys.episode_control("rig-2")),
    ("rig-1", INGRESS, QUERYABLE, keys.pod_model()),
    ("rig-1", INGRESS, QUERYABLE, keys.training("rig-2")),
    ("rig-1", INGRESS, REPLY, keys.training("rig-2")),
    ("rig-1", INGRESS, QUERY, keys.training("rig-2")),
    ("rig-1", INGRESS, QUERY, keys.training_truth_any()),
    ("rig-1", INGRESS, TOKEN, keys.alive("sensors", "evil")),
    ("rig-1", INGRESS, TOKEN, keys.alive("sensors", "rig-2")),
    ("rig-1", INGRESS, TOKEN, keys.alive("learner", "learner")),
    ("rig-1", INGRESS, TOKEN, keys.alive("orchestrator", "orchestrator")),
    ("rig-1", INGRESS, TOKEN, f"{keys.PREFIX}/alive/**"),
    ("rig-1", INGRESS, LIVELINESS_SUBSCRIBER, keys.alive_all()),
    ("rig-1", INGRESS, LIVELINESS_SUBSCRIBER, keys.alive("sensors", "rig-2")),
    ("robot-1.controller", EGRESS, TOKEN, keys.alive("sensors", "rig-1")),
    ("robot-1.controller", INGRESS, PUT, keys.measurement("robot-1")),
    ("robot-1.controller", INGRESS, PUT, keys.episode_truth("robot-1")),
    ("robot-1.controller", INGRESS, TOKEN, keys.alive("sensors", "robot-1")),
    ("robot-1.sensors", INGRESS, PUT, keys.command("robot-1")),
    ("robot-1.sensors", INGRESS, PUT, keys.episode_result("robot-1")),
    ("robot-1.sensors", INGRESS, TOKEN, keys.alive("controller", "robot-1")),
    ("learner", INGRESS, PUT, keys.episode_truth("rig-1")),
    ("learner", INGRESS, SUBSCRIBE, keys.episode_truth_all()),
    ("learner", INGRESS, QUERY, keys.training_truth_any()),
    ("orchestrator", INGRESS, PUT, keys.episode_result("rig-1")),
    ("orchestrator", INGRESS, PUT, keys.episode_truth("rig-1")),
    ("lab", INGRESS, PUT, keys.episode_result("rig-1")),
    ("lab", INGRESS, TOKEN, keys.alive("sensors", "lab")),
    ("mallory", INGRESS, PUT, keys.measurement("rig-1")),  # a user the policy does not name
    ("mallory", EGRESS, PUT, keys.measurement("rig-1")),
]


@pytest.mark.parametrize("who, flow, message, key", LEGIT)
def test_each_identity_may_do_its_own_work(who, flow, message, key):
    assert allowed(POLICY, who, flow, message, key)


@pytest.mark.parametrize("who, flow, message, key", FORBIDDEN)
def test_nobody_may_touch_another_rigs_keys_or_another_roles_plane(who, flow, message, key):
    assert not allowed(POLICY, who, flow, message, key)


def test_only_simulated_sensors_and_operators_may_put_truth():
    for identity in IDENTITIES:
        for rig in ("rig-1", "rig-2", "robot-1"):
            may = allowed(POLICY, identity.user, INGRESS, PUT, keys.episode_truth(rig))
            assert may == (identity.role == "operator" or (identity.role in ("sensors", "rig") and identity.name == rig)), identity


def test_only_the_orchestrator_may_put_on_the_control_plane():
    for identity in IDENTITIES:
        for rig in ("rig-1", "rig-2", "robot-1", "evil"):
            assert allowed(POLICY, identity.user, INGRESS, PUT, keys.episode_control(rig)) == (identity.role == "orchestrator")


def test_each_identity_may_announce_only_itself():
    names = ("rig-1", "rig-2", "robot-1", "learner", "orchestrator", "evil", "lab")
    for identity in IDENTITIES:
        own = {("sensors", identity.name), ("controller", identity.name)} if identity.role == "rig" else \
            set() if identity.role == "operator" else {(identity.role, identity.name)}
        for role in keys.ROLES:
            for name in names:
                assert allowed(POLICY, identity.user, INGRESS, TOKEN, keys.alive(role, name)) == ((role, name) in own), (identity, role, name)


def test_every_identity_learns_where_subscribers_are_and_nothing_else_by_default():
    """A declared publisher sends only once told of a matching subscriber (Zenoh 1.x), so every
    identity receives subscriber and queryable declarations; payloads still need their own rules."""
    for identity in IDENTITIES:
        assert allowed(POLICY, identity.user, EGRESS, SUBSCRIBE, keys.episode_result_all())
        assert allowed(POLICY, identity.user, EGRESS, QUERYABLE, keys.pod_model())
    assert not allowed(POLICY, "rig-2", EGRESS, PUT, keys.measurement("rig-1"))


@pytest.mark.parametrize("args, message", [
    (dict(rigs=["rig-1", "rig-1"]), "unique"),
    (dict(rigs=["rig-1"], split_rigs=["rig-1"]), "named once"),
    (dict(rigs=["learner"]), "unique"),
    (dict(rigs=["a/b"]), "letters, digits"),
    (dict(rigs=["rig-1"], operators=["x:y"]), "user name"),
])
def test_bad_identities_are_one_line_errors(args, message):
    with pytest.raises(AclError, match=message):
        standard_identities(**args)


def test_bad_policies_are_refused():
    with pytest.raises(AclError, match="at least one"):
        access_control([])
    with pytest.raises(AclError, match="match"):
        access_control(IDENTITIES, match="zid")
    with pytest.raises(AclError, match="unique"):
        access_control([Identity("a", "learner", "a"), Identity("a", "learner", "b")])
    with pytest.raises(AclError, match="role"):
        Identity("a", "admin", "a")
    assert all(g.key_exprs for i in IDENTITIES for g in grants(i))
