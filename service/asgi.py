"""ASGI pieces of the HTTP API that are not routes: the bearer-token gate, the request-body limit and the offline
API docs."""
from __future__ import annotations

import secrets
from collections.abc import Callable
from typing import Any

from fastapi import FastAPI
from fastapi.responses import JSONResponse, Response

__all__ = ["BodyLimit", "TokenGate", "offline_docs"]


class TokenGate:
    """ASGI middleware: with a token configured, a request for a protected route (`protected(scope)`: the routes
    that declare the token dependency) without `Authorization: Bearer TOKEN` is answered 401 before anything reads
    or parses its body, so that a client without the token learns nothing from the validation of what it sent (bad
    JSON was a 422 before the 401). The open routes (/healthz, /readyz, the docs, the viewer's shell) pass."""

    def __init__(self, app: Any, token: str | None, protected: Callable[[dict], bool]) -> None:
        self.app, self.token, self.protected = app, (token or "").encode(), protected

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http" or not self.token or not self.protected(scope):
            return await self.app(scope, receive, send)
        given = next((v for k, v in scope.get("headers") or [] if k.lower() == b"authorization"), b"")
        scheme, _, credentials = given.strip().partition(b" ")
        if scheme.lower() == b"bearer" and secrets.compare_digest(credentials.strip(), self.token):
            return await self.app(scope, receive, send)
        await JSONResponse({"detail": "Authorization: missing or wrong bearer token"}, status_code=401,
                           headers={"WWW-Authenticate": "Bearer"})(scope, receive, send)


class _TooLarge(Exception):
    pass


class BodyLimit:
    """ASGI middleware: request bodies above `limit` bytes are refused with 413 before a route parses them (by
    Content-Length, and by counting for chunked bodies), except on the upload route, which streams to disk under
    its own limit. A 200 MB JSON body took 2 GB of memory to parse and stalled every other request."""

    def __init__(self, app: Any, limit: int) -> None:
        self.app, self.limit = app, limit

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http" or scope["path"].endswith("/upload"):
            return await self.app(scope, receive, send)
        declared = dict(scope.get("headers") or []).get(b"content-length", b"")
        if declared.isdigit() and int(declared) > self.limit:
            return await self._refuse(send)
        seen, over, refused = 0, False, False

        async def counted() -> dict:
            nonlocal seen, over
            msg = await receive()
            if msg["type"] == "http.request":
                seen += len(msg.get("body", b""))
                if seen > self.limit:
                    over = True
                    raise _TooLarge
            return msg

        async def guarded(msg: dict) -> None:  # the route turns a failed body read into its own error: send ours
            nonlocal refused
            if not over:
                return await send(msg)
            if not refused:
                refused = True
                await self._refuse(send)

        try:
            await self.app(scope, counted, guarded)
        except _TooLarge:
            if not refused:
                await self._refuse(send)

    async def _refuse(self, send: Any) -> None:
        # a plain response never calls `receive`, so there is none to pass
        await JSONResponse({"detail": f"body: larger than the limit of {self.limit} bytes (LODCAST_MAX_BODY_BYTES)"},
                           status_code=413)({"type": "http"}, None, send)  # type: ignore[arg-type]


def offline_docs(app: FastAPI) -> None:
    """Swagger UI at /docs from the swagger-ui-bundle package's files (FastAPI's default page loads them from a
    CDN: a server without internet access showed a blank page)."""
    import swagger_ui_bundle
    from fastapi.openapi.docs import get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
    from fastapi.staticfiles import StaticFiles

    app.mount("/docs/assets", StaticFiles(directory=swagger_ui_bundle.swagger_ui_path), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    def docs() -> Response:
        return get_swagger_ui_html(openapi_url=app.openapi_url or "/openapi.json", title="lodcast API",
                                   swagger_js_url="/docs/assets/swagger-ui-bundle.js",
                                   swagger_css_url="/docs/assets/swagger-ui.css",
                                   swagger_favicon_url="/docs/assets/favicon-32x32.png",
                                   oauth2_redirect_url="/docs/oauth2-redirect")

    @app.get("/docs/oauth2-redirect", include_in_schema=False)
    def docs_redirect() -> Response:
        return get_swagger_ui_oauth2_redirect_html()
