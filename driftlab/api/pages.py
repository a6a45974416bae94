"""Pages served by the API besides its JSON: Swagger UI at /docs, ReDoc at /redoc, and their packaged assets.

FastAPI's own /docs and /redoc load Swagger UI and ReDoc from a CDN (blank without internet);
these load the copies vendored under ``static/vendor`` (see ``driftlab.api.vendor``), so the
documentation works on a shop-floor network with no way out.
"""

from __future__ import annotations

from fastapi import APIRouter, FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

from driftlab.api.vendor import STATIC

STATIC_URL = "/static"
SWAGGER = f"{STATIC_URL}/vendor/swagger-ui"
REDOC = f"{STATIC_URL}/vendor/redoc"

router = APIRouter(include_in_schema=False)


@router.get("/docs", response_class=HTMLResponse)
def swagger_ui() -> HTMLResponse:
    """Return Swagger UI on the packaged assets."""
    return get_swagger_ui_html(
        openapi_url="/openapi.json",
        title="driftlab API",
        swagger_js_url=f"{SWAGGER}/swagger-ui-bundle.js",
        swagger_css_url=f"{SWAGGER}/swagger-ui.css",
        swagger_favicon_url=f"{SWAGGER}/favicon-32x32.png",
        oauth2_redirect_url="/docs/oauth2-redirect",
    )


@router.get("/docs/oauth2-redirect", response_class=HTMLResponse)
def swagger_ui_redirect() -> HTMLResponse:
    """Return Swagger UI's OAuth2 redirect page."""
    return get_swagger_ui_oauth2_redirect_html()


@router.get("/redoc", response_class=HTMLResponse)
def redoc() -> HTMLResponse:
    """Return ReDoc on the packaged assets (no web fonts: the system's are used)."""
    return get_redoc_html(
        openapi_url="/openapi.json",
        title="driftlab API",
        redoc_js_url=f"{REDOC}/redoc.standalone.js",
        redoc_favicon_url=f"{SWAGGER}/favicon-32x32.png",
        with_google_fonts=False,
    )


def install(app: FastAPI) -> None:
    """Add the documentation pages and mount the packaged static files on ``app``."""
    app.include_router(router)
    app.mount(STATIC_URL, StaticFiles(directory=STATIC), name="static")
