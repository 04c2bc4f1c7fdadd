"""Structured logs: one JSON object per line, each carrying the id of the request it belongs to.

Every line has ``time`` (UTC, ISO 8601), ``level``, ``logger``, ``message`` and ``request_id``
(null outside a request); access lines (logger ``service.access``) add ``method``, ``path``,
``status`` and ``duration_ms``; a logged exception adds ``exc_info`` (the traceback as text).

The request id lives in a context variable that ``service.middleware.RequestContext`` sets for
the whole request, so a line logged anywhere below it (a route, a worker thread of the
threadpool, which copies the context) names its request without passing the id around.
``python -m service serve`` hands ``logging_config(level)`` to uvicorn, so uvicorn's own lines and
every worker process's lines are JSON too.
"""

from __future__ import annotations

import json
import logging
import logging.config
import re
import uuid
from contextvars import ContextVar
from datetime import UTC, datetime
from typing import Any

REQUEST_ID_HEADER = "X-Request-ID"
# An incoming id is kept if it is short printable ASCII without spaces (it is echoed in a header and
# written to logs); anything else is replaced by a fresh one.
_VALID_REQUEST_ID = re.compile(r"[\x21-\x7e]{1,128}")
ACCESS_FIELDS = ("method", "path", "status", "duration_ms")

request_id_var: ContextVar[str | None] = ContextVar("request_id", default=None)


def request_id_from(header_value: str | None) -> str:
    """The client's ``X-Request-ID`` when it is a usable id, else a new random one (32 hex chars)."""
    if header_value is not None and _VALID_REQUEST_ID.fullmatch(header_value):
        return header_value
    return uuid.uuid4().hex


class JsonFormatter(logging.Formatter):
    """A log record -> one line of JSON (see the module docstring for the fields)."""

    def format(self, record: logging.LogRecord) -> str:
        line: dict[str, Any] = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
            "request_id": getattr(record, "request_id", None) or request_id_var.get(),
        }
        for field in ACCESS_FIELDS:
            if hasattr(record, field):
                line[field] = getattr(record, field)
        if record.exc_info:
            line["exc_info"] = self.formatException(record.exc_info)
        return json.dumps(line, ensure_ascii=False, default=str)


def logging_config(level: str = "info") -> dict[str, Any]:
    """A ``logging.config.dictConfig`` dict: every logger (ours, uvicorn's, libraries') as JSON on stdout."""
    lvl = level.upper()
    handler = {"class": "logging.StreamHandler", "formatter": "json", "stream": "ext://sys.stdout"}
    return {
        "version": 1,
        "disable_existing_loggers": False,
        "formatters": {"json": {"()": JsonFormatter}},
        "handlers": {"json": handler},
        "root": {"handlers": ["json"], "level": "WARNING"},
        "loggers": {
            "service": {"handlers": ["json"], "level": lvl, "propagate": False},
            "uvicorn": {"handlers": ["json"], "level": lvl, "propagate": False},
            "uvicorn.error": {"level": lvl},
            # our middleware writes the access lines (with the request id); uvicorn's would repeat them
            "uvicorn.access": {"handlers": [], "level": "WARNING", "propagate": False},
        },
    }


def configure(level: str = "info") -> None:
    """JSON logging for this process (the build processes call it; uvicorn applies the dict itself)."""
    logging.config.dictConfig(logging_config(level))
    capture_warnings()


def capture_warnings() -> None:
    """Python warnings (a library's deprecation notice, say) go through logging when this process logs
    JSON, so they come out as JSON lines too instead of raw text among them on stderr."""
    if json_level() is not None:
        logging.captureWarnings(True)


def json_level() -> str | None:
    """The level of the ``service`` logger if this process logs it as JSON, else None.

    A build process (spawned, so it starts with logging unconfigured) logs like its parent when it
    is handed this: ``configure_like(json_level())``.
    """
    logger = logging.getLogger("service")
    if any(isinstance(h.formatter, JsonFormatter) for h in logger.handlers):
        return logging.getLevelName(logger.level).lower()
    return None


def configure_like(level: str | None) -> None:
    """``configure(level)`` when the parent process logged JSON at ``level``; nothing otherwise."""
    if level is not None:
        configure(level)
