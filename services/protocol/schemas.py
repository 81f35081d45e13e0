"""The JSON Schemas of the wire messages (``ra2vipas protocol schemas`` writes them; a recording
checks what it reads against them)."""

from __future__ import annotations


def schema_documents() -> dict[str, dict]:
    """File name -> JSON Schema of every wire message."""
    from ra2vipas.services.protocol.messages import WIRE_MESSAGES, episode_control_adapter

    docs = {f"{m.__name__}.json": m.model_json_schema() for m in WIRE_MESSAGES}
    docs["EpisodeControl.json"] = episode_control_adapter.json_schema()
    from ra2vipas.services.rigs.survey import Survey

    docs["Survey.json"] = Survey.model_json_schema()  # a file format, not a wire message: the survey rig's input
    return docs
