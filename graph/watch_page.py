"""The HTML of the ``watch`` page (see :mod:`.watch`): server-rendered, self-updating, offline."""
from __future__ import annotations

import csv
import html
import io
import json
import os
from typing import Any

IMAGE = (".png", ".svg", ".jpg", ".jpeg")
TABLE_ROWS = 200
TEXT_BYTES = 20_000
STYLE = """
body{font-family:system-ui,sans-serif;margin:1.2em;color:#222} h1{font-size:1.3em;margin:0 0 .4em}
h2{font-size:1.05em;margin:1.2em 0 .4em} .phase{display:inline-block;padding:.15em .6em;border-radius:.3em}
.ok{background:#b6d7a8}.running,.starting{background:#ffe599}.error{background:#f4cccc}
#error{white-space:pre-wrap;background:#f4cccc;padding:.6em;border-radius:.3em;font-family:monospace}
table{border-collapse:collapse;font-size:.85em;margin:.3em 0} td,th{border:1px solid #ccc;padding:.15em .45em;text-align:left}
.state-cached{background:#d9ead3}.state-ran{background:#b6d7a8}.state-running{background:#ffe599}
.state-queued{background:#fce5cd}.state-failed{background:#f4cccc}.state-skipped{background:#eee}
img.out{max-width:48%;border:1px solid #ccc;margin:.2em;vertical-align:top;background:#fff}
iframe{width:100%;height:480px;border:1px solid #ccc} pre{background:#f6f6f6;padding:.5em;overflow:auto;max-height:360px}
#pipeline{display:flex;gap:1em;align-items:flex-start} #graph{flex:1;max-height:520px;overflow:auto;border:1px solid #ddd}
#graph img{max-width:100%}
"""
SCRIPT = """
const shown = %(shown)s;
async function tick() {
  try {
    const s = await (await fetch('/state.json', {cache: 'no-store'})).json();
    if (s.result_version !== shown.result_version) { location.reload(); return; }
    const phase = document.getElementById('phase');
    phase.textContent = s.phase + (s.phase === 'ok' ? ' - ' + s.summary : '');
    phase.className = 'phase ' + s.phase;
    const error = document.getElementById('error');
    error.textContent = s.error; error.hidden = !s.error;
    document.getElementById('runs').textContent = s.runs;
    const rows = s.nodes.map(n => `<tr class="state-${n.state}"><td>${n.node}</td><td>${n.branches}</td>` +
                                   `<td data-state="${n.state}">${n.state}</td></tr>`).join('');
    document.getElementById('nodes').innerHTML = '<tr><th>node</th><th>branches</th><th>state</th></tr>' + rows;
    if (s.version !== shown.version) {
      shown.version = s.version;
      const img = document.getElementById('graph-img');
      if (img) img.src = '/graph.svg?v=' + s.version;
    }
  } catch (e) { document.getElementById('phase').textContent = 'watch stopped'; }
  setTimeout(tick, 1000);
}
tick();
"""


def _esc(value: Any) -> str:
    return html.escape(str(value))


def _table(rows: list[dict[str, Any]]) -> str:
    columns: list[str] = []
    for row in rows[:TABLE_ROWS]:
        columns += [k for k in row if k not in columns]
    head = "".join(f"<th>{_esc(c)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{_esc(_short(row.get(c, '')))}</td>" for c in columns) + "</tr>"
                   for row in rows[:TABLE_ROWS])
    return f"<table><tr>{head}</tr>{body}</table>"


def _short(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    text = value if isinstance(value, str) else json.dumps(value)
    return text if len(text) <= 80 else text[:79] + "…"


def _row_lists(value: Any, path: str = "") -> list[tuple[str, list[dict[str, Any]]]]:
    """Lists of flat records inside a JSON value (e.g. one row per mapped branch), with where they are."""
    found = []
    if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        found.append((path or "(top)", value))
    elif isinstance(value, dict):
        for key, v in value.items():
            found += _row_lists(v, f"{path}.{key}" if path else key)
    return found[:4]


def _json_view(data: bytes) -> str:
    try:
        value = json.loads(data)
    except ValueError:
        return f"<pre>{_esc(data[:TEXT_BYTES].decode('utf-8', 'replace'))}</pre>"
    tables = "".join(f"<p>{_esc(where)}</p>{_table(rows)}" for where, rows in _row_lists(value))
    scalars = {k: v for k, v in value.items() if not isinstance(v, (dict, list))} if isinstance(value, dict) else {}
    text = json.dumps(value, indent=1)
    return (_table([scalars]) if scalars else "") + tables + \
        f"<details><summary>JSON</summary><pre>{_esc(text[:TEXT_BYTES])}</pre></details>"


def _csv_view(data: bytes) -> str:
    rows = list(csv.DictReader(io.StringIO(data.decode("utf-8", "replace"))))
    return _table(rows)


def _file_view(out_dir: str, rel: str) -> str:
    url = "/files/" + _esc(rel)
    ext = os.path.splitext(rel)[1].lower()
    if ext in IMAGE:
        return f'<img class="out" src="{url}" alt="{_esc(rel)}" title="{_esc(rel)}">'
    if ext == ".html":
        return f'<iframe src="{url}" title="{_esc(rel)}"></iframe>'
    if ext in (".json", ".csv"):
        try:
            with open(os.path.join(out_dir, *rel.split("/")), "rb") as f:
                data = f.read()
        except OSError:
            return ""
        return _json_view(data) if ext == ".json" else _csv_view(data)
    return ""


def render_page(state: dict[str, Any], out_dir: str) -> str:
    files = [f["path"] for f in state["files"]]
    sections = []
    for kind, test in (("Images", lambda p: p.lower().endswith(IMAGE)), ("Previews", lambda p: p.endswith(".html")),
                       ("Tables", lambda p: p.endswith((".json", ".csv")))):
        chosen = [p for p in files if test(p)]
        if chosen:
            views = "".join(f'<div class="file" data-path="{_esc(p)}"><h3>{_esc(p)}</h3>{_file_view(out_dir, p)}</div>'
                            if kind != "Images" else _file_view(out_dir, p) for p in chosen)
            sections.append(f"<h2>{kind}</h2>{views}")
    others = [p for p in files if not p.lower().endswith(IMAGE + (".html", ".json", ".csv"))]
    if others:
        sections.append("<h2>Other files</h2><ul>" + "".join(f'<li><a href="/files/{_esc(p)}">{_esc(p)}</a></li>'
                                                            for p in others) + "</ul>")
    shown = json.dumps({"version": state["version"], "result_version": state["result_version"]})
    nodes = "".join(f'<tr class="state-{n["state"]}"><td>{_esc(n["node"])}</td><td>{n["branches"]}</td>'
                    f'<td data-state="{n["state"]}">{n["state"]}</td></tr>' for n in state["nodes"])
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>watch {_esc(state['pipeline'])}</title>
<style>{STYLE}</style></head><body>
<h1>{_esc(state['pipeline'])} <span id="phase" class="phase {state['phase']}">{_esc(state['phase'])}</span></h1>
<p>runs: <span id="runs">{state['runs']}</span>; last good output: {_esc(state['out_dir'])}</p>
<div id="error"{'' if state['error'] else ' hidden'}>{_esc(state['error'])}</div>
<div id="pipeline"><table id="nodes"><tr><th>node</th><th>branches</th><th>state</th></tr>{nodes}</table>
<div id="graph"><img id="graph-img" src="/graph.svg?v={state['version']}" alt="" onerror="this.remove()"></div></div>
<div id="result" data-result-version="{state['result_version']}">{''.join(sections) or '<p>no result yet</p>'}</div>
<script>{SCRIPT % {'shown': shown}}</script></body></html>"""
