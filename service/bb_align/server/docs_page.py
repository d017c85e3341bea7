"""The REST reference at /docs as one self-contained page.

FastAPI's default /docs and /redoc load Swagger UI and ReDoc from a CDN, which is blank on a vehicle network with no
internet. This page is made from the OpenAPI schema on the service itself and loads nothing else; the full schema
is at /openapi.json for any OpenAPI viewer or client generator."""

from __future__ import annotations

from html import escape

_STYLE = (
    "body{font-family:sans-serif;margin:2em;max-width:70em}table{border-collapse:collapse}"
    "td,th{border:1px solid #ccc;padding:.3em .6em;text-align:left;vertical-align:top}code{font-size:1.05em}"
)


def docs_html(schema: dict) -> str:
    """Every path and method with its summary and response codes, and a link to the schema."""
    info = schema.get("info", {})
    title = escape(f"{info.get('title', '')} {info.get('version', '')}".strip())
    rows = []
    for path, operations in schema.get("paths", {}).items():
        for method, op in operations.items():
            codes = ", ".join(sorted(op.get("responses", {})))
            rows.append(
                f"<tr><td>{escape(method.upper())}</td><td><code>{escape(path)}</code></td>"
                f"<td>{escape(op.get('summary', ''))}</td><td>{escape(codes)}</td></tr>"
            )
    return (
        f'<!doctype html><html><head><meta charset="utf-8"><title>{title} REST API</title>'
        f"<style>{_STYLE}</style></head><body><h1>{title} REST API</h1>"
        f"<p>{escape(info.get('description', ''))}</p>"
        '<p>The OpenAPI schema (bodies, answers, errors): <a href="/openapi.json">/openapi.json</a>. This page is '
        "served by the service and loads nothing from the internet.</p>"
        "<table><tr><th>method</th><th>path</th><th>what</th><th>answers</th></tr>"
        + "".join(rows)
        + "</table></body></html>"
    )
