"""One self-contained HTML page of an evaluation: `report.html` beside `evaluate`'s tables.

Everything is inside the file (pictures as base64 data URIs, no scripts, no network): the tables of
`table.md`, the common-sense bar chart and distribution plots, the grid of generated scenes next to
the ground truth on the same maps, the checkpoint's step and config, and the data split with the
scenes used and skipped. It opens in any browser, offline, and can be mailed as it is.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

from tdiff_jax import files

_STYLE = """
body { font-family: sans-serif; max-width: 1100px; margin: 2em auto; color: #222; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.85em; }
th, td { border: 1px solid #bbb; padding: 0.2em 0.5em; text-align: right; }
th { background: #eee; } td:first-child, td:nth-child(2) { text-align: left; }
img { max-width: 100%; border: 1px solid #ddd; margin: 0.3em 0; }
.plots img { width: 49%; } pre { background: #f6f6f6; padding: 0.6em; font-size: 0.75em; overflow-x: auto; }
"""


def image_tag(path: Path | str, alt: str) -> str:
  """`<img>` with the PNG (or GIF) embedded as a data URI."""
  path = Path(path)
  kind = "gif" if path.suffix.lower() == ".gif" else "png"
  data = base64.b64encode(path.read_bytes()).decode()
  return f'<img alt="{html.escape(alt)}" src="data:image/{kind};base64,{data}">'


def markdown_to_html(markdown: str) -> str:
  """The subset of Markdown `evaluate.to_markdown` writes: paragraphs, bullet lines, pipe tables,
  `code` and **bold**."""
  out, table = [], []

  def inline(text: str) -> str:
    text = html.escape(text)
    parts = text.split("`")
    text = "".join(f"<code>{p}</code>" if i % 2 else p for i, p in enumerate(parts))
    parts = text.split("**")
    return "".join(f"<b>{p}</b>" if i % 2 else p for i, p in enumerate(parts))

  def flush_table():
    if table:
      head, *body = [[c.strip() for c in row.strip().strip("|").split("|")] for row in table if "---" not in row]
      out.append("<table><tr>" + "".join(f"<th>{inline(c)}</th>" for c in head) + "</tr>"
                 + "".join("<tr>" + "".join(f"<td>{inline(c)}</td>" for c in row) + "</tr>" for row in body)
                 + "</table>")
      table.clear()

  for line in markdown.splitlines():
    if line.startswith("|"):
      table.append(line)
      continue
    flush_table()
    if line.startswith("- "):
      out.append(f"<li>{inline(line[2:])}</li>")
    elif line.strip():
      out.append(f"<p>{inline(line)}</p>")
  flush_table()
  return "\n".join(out)


def write_report(path: Path | str, result: dict, markdown: str, rates: Path | None = None,
                 distributions: list[Path] = (), grid: Path | None = None, realism: Path | None = None) -> Path:
  """Writes the page (atomically) and returns its path."""
  parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>tdiff_jax evaluation</title>"
           f"<style>{_STYLE}</style></head><body>", "<h1>tdiff_jax evaluation</h1>"]
  used, skipped = result["scenes"], len(result["skipped"])
  parts.append(f"<p>Data: <code>{html.escape(result['data'])}</code>: {used} scenes used, {skipped} skipped, "
               f"{result['agents']} ground-truth agents; {result['seconds']} s.</p>")
  for key, name in (("hl_checkpoint", "HL checkpoint"), ("infill_checkpoint", "infiller checkpoint")):
    if key in result:
      ck = result[key]
      parts.append(f"<p>{name}: <code>{html.escape(ck['workdir'])}</code>, step {ck['step']}"
                   + (f", sampler {html.escape(ck['sampler']['description'])}" if "sampler" in ck else "") + ".</p>")
  parts += ["<h2>Tables</h2>", markdown_to_html(markdown)]
  if rates is not None:
    parts += ["<h2>Common-sense metrics</h2>", image_tag(rates, "collision, off-road and near edge")]
  if distributions:
    parts += ["<h2>Distributions (ground truth and model)</h2>", "<div class='plots'>"]
    parts += [image_tag(p, p.stem) for p in distributions] + ["</div>"]
  if realism is not None:
    parts += ["<h2>Realism features (logged and generated)</h2>", image_tag(realism, "realism feature histograms")]
  if grid is not None:
    parts += ["<h2>Generated scenes next to the ground truth, same maps</h2>", image_tag(grid, "scene grid")]
  config = result.get("hl_checkpoint", {}).get("config")
  if config is not None:
    parts += ["<h2>HL checkpoint config</h2>", f"<pre>{html.escape(json.dumps(config, indent=1))}</pre>"]
  parts.append("</body></html>")
  files.atomic_write_text(path, "\n".join(parts))
  return Path(path)
