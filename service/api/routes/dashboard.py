"""/: a minimal HTML list of jobs that refreshes itself (the real dashboard is
a later issue)."""

from __future__ import annotations

from html import escape

from fastapi import APIRouter
from fastapi.responses import HTMLResponse

from ... import jobs
from ..deps import SessionDep

router = APIRouter(tags=["dashboard"])

_PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><meta http-equiv="refresh" content="2">
<title>rayfarm</title>
<style>body{{font-family:sans-serif;margin:2em}}table{{border-collapse:collapse}}
td,th{{padding:.3em .8em;border-bottom:1px solid #ddd;text-align:left}}</style></head>
<body><h1>rayfarm</h1><p><a href="/docs">API</a></p>
<table><tr><th>job</th><th>status</th><th>scene</th><th>method</th><th>spp</th>
<th>size</th><th>progress</th><th>image</th><th>error</th></tr>
{rows}
</table></body></html>"""


@router.get("/", response_class=HTMLResponse, include_in_schema=False)
def index(session: SessionDep) -> str:
    rows = []
    for job in jobs.list_jobs(session, limit=200):
        image = (f'<a href="/jobs/{job.id}/result.exr">exr</a> ' if job.status == "done" else ""
                 ) + (f'<a href="/jobs/{job.id}/preview.png">png</a>'
                      if job.status == "done" or job.units_done else "")
        rows.append(
            f'<tr><td><a href="/jobs/{job.id}">{escape(job.id)}</a></td>'
            f"<td>{escape(job.status)}</td><td>{escape(job.scene)}</td>"
            f"<td>{escape(str(job.spec.get('method')))}</td><td>{job.spec.get('spp')}</td>"
            f"<td>{job.width}&times;{job.height}</td>"
            f"<td>{job.units_done}/{job.units_total}</td><td>{image}</td>"
            f"<td>{escape(job.error or '')}</td></tr>")
    return _PAGE.format(rows="\n".join(rows) or '<tr><td colspan="9">no jobs yet</td></tr>')
