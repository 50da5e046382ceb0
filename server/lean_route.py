"""`LeanRoute`: a route documented from its endpoint's signature like any FastAPI route, but
served without FastAPI's per-request machinery.

The label API's hot routes (next, submit) spent nearly as much CPU in FastAPI's request handling
as in their queue work (`benchmarks/bench_queue_ops.py --app`): solving the dependency tree,
validating each parameter group in turn, parsing the content type with the `email` package, and
building the endpoint's error context, on every request. A LeanRoute prepares once, when the app
is built, one pydantic model for the path and query parameters and one validator for the JSON
body, and on each request calls the dependencies with the request, validates, and calls the
endpoint. Its refusals are FastAPI's: a 422 `RequestValidationError` whose `loc` starts with
"path", "query" or "body", a 400 for a body that is not UTF-8 or is nested too deeply to decode
(FastAPI answers 400 to any decoding error but malformed JSON), and the dependencies' own HTTP
errors, in the order FastAPI gives them.

It serves the endpoints FastAPI would, within limits that are checked when the route is made:
- each dependency is an `async def` of the request alone, with no dependencies of its own;
- the parameters are path and query parameters (scalars) and at most one JSON body;
- the endpoint is an `async def` that returns a `Response`;
- `app.dependency_overrides` does not apply to it.
"""

from __future__ import annotations

import inspect
import json
from collections.abc import Callable, Coroutine
from typing import Any

from fastapi import HTTPException, Request, Response
from fastapi.dependencies.models import Dependant
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute
from pydantic import BaseModel, ValidationError, create_model

Handler = Callable[[Request], Coroutine[Any, Any, Response]]


def _unsupported(route: APIRoute, why: str) -> TypeError:
    return TypeError(f"{route.path}: a LeanRoute {why}; use a plain APIRoute")


def _request_dependencies(route: APIRoute) -> list[tuple[str, Callable[..., Any]]]:
    """(parameter name, call) of each dependency, each an async function of the request."""
    found = []
    for dependency in route.dependant.dependencies:
        call = dependency.call
        if (
            dependency.name is None
            or call is None
            or not inspect.iscoroutinefunction(call)
            or dependency.dependencies
            or dependency.request_param_name is None
            or len(inspect.signature(call).parameters) != 1
        ):
            raise _unsupported(route, "takes only async dependencies of the request alone")
        found.append((dependency.name, call))
    return found


def _check_parameters(route: APIRoute) -> None:
    dependant: Dependant = route.dependant
    extra = (
        dependant.header_params or dependant.cookie_params or dependant.background_tasks_param_name
        or dependant.response_param_name or dependant.websocket_param_name
        or dependant.security_scopes_param_name or len(dependant.body_params) > 1
    )
    if extra:
        raise _unsupported(route, "takes path and query parameters and one JSON body only")
    if not inspect.iscoroutinefunction(dependant.call):
        raise _unsupported(route, "serves an async endpoint")


def _is_json(content_type: str) -> bool:
    kind = content_type.partition(";")[0].strip().lower()
    return kind == "application/json" or (
        kind.startswith("application/") and kind.endswith("+json")
    )


class LeanRoute(APIRoute):
    """An APIRoute whose requests are served by the handler below (see the module's text)."""

    def get_route_handler(self) -> Handler:
        _check_parameters(self)
        dependencies = _request_dependencies(self)
        endpoint: Callable[..., Coroutine[Any, Any, Response]] = self.dependant.call  # type: ignore[assignment]
        request_name = self.dependant.request_param_name
        fields = [(f, "path") for f in self.dependant.path_params] + [
            (f, "query") for f in self.dependant.query_params
        ]
        where = {f.name: (location, f.alias) for f, location in fields}
        params: type[BaseModel] | None = (
            create_model(  # type: ignore[call-overload]
                f"{self.name}_parameters",
                **{f.name: (f.field_info.annotation, f.field_info) for f, _ in fields},
            )
            if fields
            else None
        )
        body_field = self.body_field
        body_name = body_field.name if body_field is not None else None

        def parameters(request: Request) -> tuple[dict[str, Any], list[dict[str, Any]]]:
            assert params is not None
            given: dict[str, Any] = {}
            for name, (location, alias) in where.items():
                source = request.path_params if location == "path" else request.query_params
                if alias in source:
                    given[name] = source[alias]
            try:
                return dict(params.model_validate(given)), []
            except ValidationError as error:
                return {}, [
                    {**e, "loc": (*where[str(e["loc"][0])], *e["loc"][1:])}
                    for e in error.errors(include_url=False)
                ]

        async def decoded_body(request: Request) -> Any:
            """The body as FastAPI reads it before anything else: decoded JSON for a JSON
            content type (refused at once if it is not JSON), else the bytes; None if empty."""
            raw = await request.body()
            if not raw:
                return None
            if not _is_json(request.headers.get("content-type", "")):
                return raw  # validated as bytes, so refused as FastAPI does
            try:
                return json.loads(raw)
            except json.JSONDecodeError as error:
                raise RequestValidationError([{
                    "type": "json_invalid", "loc": ("body", error.pos),
                    "msg": "JSON decode error", "input": {}, "ctx": {"error": error.msg},
                }]) from None
            except (ValueError, RecursionError):  # not UTF-8 text, or nested too deep to decode
                raise HTTPException(400, "There was an error parsing the body") from None

        def validated_body(value: Any) -> tuple[Any, list[dict[str, Any]]]:
            assert body_field is not None
            if value is None:
                return None, [{"type": "missing", "loc": ("body",), "msg": "Field required",
                               "input": None}]
            try:
                parsed, errors = body_field.validate(value, loc=("body",))
            except RecursionError:  # a value nested some 900 levels deep, refused by repr()
                return None, [{"type": "value_error", "loc": ("body",), "input": None,
                               "msg": "Value error, the body is nested too deeply"}]
            for refusal in errors:  # FastAPI sends bytes as text, failing on invalid UTF-8
                if isinstance(refusal.get("input"), bytes):
                    refusal["input"] = refusal["input"].decode(errors="replace")
            return parsed, errors

        async def handle(request: Request) -> Response:
            # FastAPI's order: the body is read and decoded, the dependencies are called, then
            # every parameter is validated and all refusals are reported together.
            raw_body = await decoded_body(request) if body_field is not None else None
            kwargs: dict[str, Any] = {name: await call(request) for name, call in dependencies}
            if request_name is not None:
                kwargs[request_name] = request
            errors: list[dict[str, Any]] = []
            if params is not None:
                values, errors = parameters(request)
                kwargs.update(values)
            if body_field is not None:
                kwargs[body_name], body_errors = validated_body(raw_body)  # type: ignore[index]
                errors += body_errors
            if errors:
                raise RequestValidationError(errors)
            response = await endpoint(**kwargs)
            if not isinstance(response, Response):
                raise TypeError(f"{self.path}: a LeanRoute's endpoint returns a Response")
            return response

        return handle
