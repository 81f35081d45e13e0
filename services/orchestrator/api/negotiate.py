"""Which representation a client asked for: ``?format=`` first, then the ``Accept`` header."""

from __future__ import annotations

from typing import Literal, Optional

from fastapi import Request

ResultsFormat = Literal["json", "csv"]
ImageFormat = Literal["png", "svg"]


def results_format(request: Request, fmt: Optional[str]) -> str:
    if fmt:
        return fmt
    accept = request.headers.get("accept", "")
    return "csv" if "text/csv" in accept and "application/json" not in accept else "json"


def image_format(request: Request, fmt: Optional[str]) -> str:
    if fmt:
        return fmt
    accept = request.headers.get("accept", "")
    return "svg" if "image/svg+xml" in accept and "image/png" not in accept else "png"


IMAGE_CONTENT = {
    "image/png": {"schema": {"type": "string", "format": "binary"}},
    "image/svg+xml": {"schema": {"type": "string"}},
}
