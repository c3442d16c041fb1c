"""``/docs``: Swagger UI served by the app itself, so the API page works without internet.

Swagger UI's files come from the ``fastapi-offline`` package (its ``static/`` folder: the
``swagger-ui-dist`` bundle and stylesheet); our page and its init script (``apidocs/``) load them
from ``/docs-assets/``. The init is an external script, so the page runs under a CSP without
inline scripts (:data:`~.browser.DOCS_CSP`). Every URL in the page is relative, so the page also
works behind a proxy that serves the app under a path prefix.

Build the app with ``docs_url=None, redoc_url=None`` and call :func:`add_docs`.
"""

from __future__ import annotations

import html
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

from .browser import DOCS_CSP

DOCS_PATH = "/docs"
ASSETS_PATH = "/docs-assets"  #: our init script and Swagger UI's files, one folder of URLs
APIDOCS_DIR = Path(__file__).with_name("apidocs")  #: package data of the wheel
SWAGGER_UI = ("fastapi_offline", "static")  #: (package, folder) holding swagger-ui-bundle.js and swagger-ui.css

_PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title} · API</title>
<link rel="icon" type="image/png" href="{assets}/favicon.png">
<link rel="stylesheet" href="{assets}/swagger-ui.css">
</head>
<body>
<div id="swagger-ui" data-openapi-url="{openapi}"></div>
<script src="{assets}/swagger-ui-bundle.js"></script>
<script src="{assets}/swagger-init.js"></script>
</body>
</html>
"""


def docs_page(title: str, openapi_url: str) -> str:
    """The /docs HTML: Swagger UI's stylesheet and bundle and our init script, all from this app
    (URLs relative to /docs, which is at the root)."""
    return _PAGE.format(title=html.escape(title), assets=ASSETS_PATH.lstrip("/"),
                        openapi=html.escape(openapi_url.lstrip("/")))


def add_docs(app: FastAPI) -> None:
    """Serve Swagger UI at :data:`DOCS_PATH` and its files under :data:`ASSETS_PATH` (add before a
    catch-all mount such as the dashboard's at ``/``)."""
    if app.openapi_url is None:
        raise ValueError("the docs page needs the app's OpenAPI document (openapi_url)")
    page = docs_page(app.title, app.openapi_url)
    app.mount(ASSETS_PATH, StaticFiles(directory=APIDOCS_DIR, packages=[SWAGGER_UI]), name="docs-assets")

    @app.get(DOCS_PATH, include_in_schema=False)
    async def docs() -> HTMLResponse:
        return HTMLResponse(page, headers={"Content-Security-Policy": DOCS_CSP})
