"""The web page at ``/`` (files owned by the web part, in ``service/static``).

A StaticFiles mount at ``/`` matches every path, so a wrong method on an API path would
get the mount's ``405 Allow: GET, HEAD`` instead of the API's. This wrapper answers for
API paths from the app's own routes: 405 with the route's real methods, else 404.
"""
from __future__ import annotations

from starlette.routing import Match
from starlette.staticfiles import StaticFiles
from starlette.types import Receive, Scope, Send

from .errors import Problem, problem_response


METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE")


class SiteFiles(StaticFiles):
    def __init__(self, *args, routes: list, **kwargs) -> None:  # noqa: ANN002, ANN003
        super().__init__(*args, **kwargs)
        self.routes = routes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            # probe each method: routes may be wrapped (included routers) without .methods
            allowed = {method for method in METHODS
                       if any(route.matches({**scope, "method": method})[0] is Match.FULL for route in self.routes)}
            if allowed:
                problem = Problem(405, f"{scope['method']} is not allowed here; use {', '.join(sorted(allowed))}",
                                  headers={"Allow": ", ".join(sorted(allowed))})
                await problem_response(problem)(scope, receive, send)
                return
            if scope["path"].startswith("/v1/"):
                await problem_response(Problem(404, f"no such endpoint: {scope['path']}",
                                               slug="not-found"))(scope, receive, send)
                return
        await super().__call__(scope, receive, send)
