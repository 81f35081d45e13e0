"""How a node reads the replies to its queries: the first usable one, and why others were not."""

from __future__ import annotations

from ra2vipas.services.protocol.messages import ErrorReply, PODRequest, TrainingRequest, dump
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.transport.bus import Reply
from ra2vipas.services.transport.runtime import first_valid_reply


def _request(job: str) -> bytes:
    return dump(TrainingRequest(job_id=job, scenario=build_scenario("paper"), seed=1))


def test_the_first_valid_accepted_reply_wins_and_the_others_say_why_they_were_passed_over():
    replies = [
        Reply("k", dump(ErrorReply(error="sensors busy")), ok=False),
        Reply("k", b"plain text failure", ok=False),
        Reply("k", b'{"job_id": 3}'),
        Reply("k", _request("other-job")),
        Reply("k", _request("wanted")),
        Reply("k", _request("wanted-too")),
    ]
    message, passed_over = first_valid_reply(replies, TrainingRequest, "TrainingRequest", accept=lambda r: r.job_id.startswith("wanted"))
    assert message is not None and message.job_id == "wanted"
    assert passed_over[:2] == ["sensors busy", "plain text failure"]
    assert passed_over[2].startswith("malformed TrainingRequest: ") and len(passed_over) == 3


def test_no_usable_reply_gives_none_and_every_reason():
    assert first_valid_reply([], PODRequest, "PODRequest") == (None, [])
    message, passed_over = first_valid_reply([Reply("k", b"nope", ok=False), Reply("k", b"[]")], PODRequest, "PODRequest")
    assert message is None
    assert passed_over[0] == "nope" and passed_over[1].startswith("malformed PODRequest: ")
