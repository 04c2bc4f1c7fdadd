"""openapi.json (project root) is the app's own schema; regenerate it with ``python -m service.openapi``."""

from __future__ import annotations

import json

from service.main import create_app
from service.openapi import OPENAPI_PATH, render

ERROR_REF = "#/components/schemas/Error"


def test_openapi_json_is_up_to_date():
    schema = create_app().openapi()
    assert json.loads(OPENAPI_PATH.read_text()) == schema, "run: python -m service.openapi"
    assert OPENAPI_PATH.read_text() == render(schema)  # pretty, sorted keys


def test_error_responses_use_the_error_schema():
    paths = create_app().openapi()["paths"]
    expected = {
        ("/models", "post"): {"413", "415", "422"},
        ("/models/{model_id}", "get"): {"404"},
        ("/models/{model_id}", "delete"): {"404"},
        ("/models/{model_id}/templates/{k}.png", "get"): {"404", "409", "422"},
        ("/models/{model_id}/estimate", "post"): {"404", "409", "413", "415", "422"},
        ("/models/{model_id}/grasps", "put"): {"404", "422"},
        ("/models/{model_id}/grasps", "get"): {"404"},
        ("/models/{model_id}/references", "post"): {"404", "409", "413", "415", "422"},
        ("/models/{model_id}/references", "get"): {"404"},
        ("/models/{model_id}/references", "delete"): {"404"},
        ("/cameras/{name}", "put"): {"422"},
        ("/cameras/{name}", "get"): {"404", "422"},
        ("/cameras/{name}", "delete"): {"404", "422"},
    }
    for (path, method), codes in expected.items():
        responses = paths[path][method]["responses"]
        assert codes <= set(responses), (path, method)
        for code, resp in responses.items():
            if code.startswith("4"):
                assert resp["content"]["application/json"]["schema"]["$ref"] == ERROR_REF, (path, code)
    assert "HTTPValidationError" not in json.dumps(paths)  # 422 is {"detail": "<sentence>"} too
