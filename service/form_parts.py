"""A multipart form part holding JSON -> a wire model (``service.schemas``), with one-sentence 422s: bad
JSON, a non-object, NaN or Infinity, nesting too deep, or the model's own validation."""

from __future__ import annotations

import json
import math
import re
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from service.errors import UnprocessableError, validation_sentence

M = TypeVar("M", bound=BaseModel)


def _finite(v: Any) -> bool:
    if isinstance(v, float):
        return math.isfinite(v)
    if isinstance(v, dict):
        return all(_finite(x) for x in v.values())
    if isinstance(v, list):
        return all(_finite(x) for x in v)
    return True


MAX_JSON_DEPTH = 16  # the deepest any part's JSON needs is 2 (distance_range_mm, dist)
_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')
_NOT_BRACKET = re.compile(r"[^\[\]{}]+")
_JSON_TYPES = {dict: "an object", list: "an array", str: "a string", bool: "a boolean", int: "a number",
               float: "a number", type(None): "null"}


def json_depth(text: str) -> int:
    """How deeply ``text``'s arrays and objects nest (brackets inside strings do not count); linear."""
    depth = deepest = 0
    for ch in _NOT_BRACKET.sub("", _JSON_STRING.sub("", text)):
        depth += 1 if ch in "[{" else -1
        deepest = max(deepest, depth)
    return deepest


def parse_json_object(text: str | None, what: str) -> dict[str, Any]:
    """A form part holding a JSON object -> dict; 422 (one sentence) on bad JSON, non-objects, NaN or
    nesting deeper than ``MAX_JSON_DEPTH`` (checked before parsing: 100,000 brackets made json.loads
    raise RecursionError, a 500)."""
    if text is None or not text.strip():
        return {}
    if json_depth(text) > MAX_JSON_DEPTH:
        raise UnprocessableError(f"The {what} part nests arrays or objects more than {MAX_JSON_DEPTH} levels "
                                 "deep; send a flat JSON object such as {\"key\": value}")
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        raise UnprocessableError(f"The {what} part is not valid JSON ({e.msg} at character {e.pos}); send a "
                                 "JSON object such as {\"key\": value}") from e
    except RecursionError as e:  # a guard behind the depth check
        raise UnprocessableError(f"The {what} part nests too deeply; send a flat JSON object") from e
    if not isinstance(value, dict):
        got = _JSON_TYPES.get(type(value), type(value).__name__)
        raise UnprocessableError(f"The {what} part must be a JSON object, not {got}; send {{\"key\": value, "
                                 "...}} or leave the part out")
    if not _finite(value):
        raise UnprocessableError(f"The {what} part contains NaN or Infinity; send finite numbers only")
    return value


def parse_json_part(text: str | None, model: type[M], what: str) -> M:
    """A form part holding JSON -> the wire model; 422 with one sentence naming the first problem."""
    return validate_part(parse_json_object(text, what), model, what)


def validate_part(value: dict[str, Any], model: type[M], what: str) -> M:
    """A form part's parsed JSON object -> the wire model; 422 with one sentence naming the first problem."""
    try:
        return model.model_validate(value)
    except ValidationError as e:
        raise UnprocessableError(validation_sentence(e.errors(), what=what)) from e
