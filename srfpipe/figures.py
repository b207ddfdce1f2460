"""Figures for the evaluation folder and the Snakemake report, with no plotting library: the
training curve as a small SVG line chart, and the metrics as an HTML table.

    svg = training_curve_svg(read_curve(srf), read_curve(srf, "eval_curve"))
    html = metrics_html(json.loads(Path("eval/metrics.json").read_text()), title="orchard")
"""

from __future__ import annotations

import html
import math

import numpy as np

COLOURS = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b"]


def _ticks(lo: float, hi: float, log: bool) -> list[tuple[float, str]]:
    """(value, label) of the ticks: powers of ten on a log axis, else 1, 2 or 5 x 10^k apart."""
    if log:
        return [(10.0**e, f"{10.0**e:g}") for e in range(math.floor(math.log10(lo)), math.ceil(math.log10(hi)) + 1)]
    if not hi > lo:
        return [(lo, f"{lo:.4g}")]
    raw = (hi - lo) / 4
    magnitude = 10.0 ** math.floor(math.log10(raw))
    step = min((m * magnitude for m in (1, 2, 5, 10) if m * magnitude >= raw), default=10 * magnitude)
    decimals = max(0, -math.floor(math.log10(step)))
    first = math.ceil(lo / step - 1e-9)
    values = [k * step for k in range(first, math.floor(hi / step + 1e-9) + 1)]
    return [(v, f"{v:.{decimals}f}") for v in values]


def line_chart_svg(panels: list[dict], x_label: str, width: int = 330, height: int = 240) -> str:
    """Panels side by side; each {"title", "series": {name: (xs, ys)}, "log": bool}. Non-finite
    points (and non-positive ones on a log axis) are left out; a panel without points says so."""
    pad_left, pad_right, pad_top, pad_bottom = 52, 12, 28, 42
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width * len(panels)}" height="{height}" '
             f'font-family="sans-serif" font-size="11"><rect width="100%" height="100%" fill="white"/>']
    for p, panel in enumerate(panels):
        log = bool(panel.get("log"))
        x0, y0 = p * width + pad_left, pad_top
        w, h = width - pad_left - pad_right, height - pad_top - pad_bottom
        series = {}
        for name, (xs, ys) in panel["series"].items():
            xs, ys = np.asarray(xs, dtype=np.float64), np.asarray(ys, dtype=np.float64)
            ok = np.isfinite(xs) & np.isfinite(ys) & ((ys > 0) if log else True)
            if ok.any():
                series[name] = (xs[ok], np.log10(ys[ok]) if log else ys[ok])
        parts.append(f'<text x="{x0}" y="16" font-weight="bold">{html.escape(panel["title"])}</text>')
        parts.append(f'<rect x="{x0}" y="{y0}" width="{w}" height="{h}" fill="none" stroke="#444"/>')
        parts.append(f'<text x="{x0 + w / 2:.0f}" y="{height - 6}" text-anchor="middle">{html.escape(x_label)}</text>')
        if not series:
            parts.append(f'<text x="{x0 + w / 2:.0f}" y="{y0 + h / 2:.0f}" text-anchor="middle">no data</text>')
            continue
        all_x = np.concatenate([s[0] for s in series.values()])
        all_y = np.concatenate([s[1] for s in series.values()])
        xlo, xhi = float(all_x.min()), float(all_x.max())
        ylo, yhi = float(all_y.min()), float(all_y.max())
        if log:
            ylo, yhi = math.floor(ylo), math.ceil(yhi)
        y_ticks = _ticks(10.0**ylo if log else ylo, 10.0**yhi if log else yhi, log)
        x_ticks = _ticks(xlo, xhi, False)
        # one point (or a flat line) sits in the middle of its axis
        xlo, xhi = (xlo, xhi) if xhi > xlo else (xlo - 1.0, xhi + 1.0)
        ylo, yhi = (ylo, yhi) if yhi > ylo else (ylo - 1.0, yhi + 1.0)

        def at(x, y):
            return x0 + (x - xlo) / (xhi - xlo) * w, y0 + h - (y - ylo) / (yhi - ylo) * h

        for tick, label in y_ticks:
            _, y = at(xlo, math.log10(tick) if log else tick)
            parts.append(f'<line x1="{x0}" x2="{x0 + w}" y1="{y:.1f}" y2="{y:.1f}" stroke="#ddd"/>')
            parts.append(f'<text x="{x0 - 4}" y="{y + 4:.1f}" text-anchor="end">{label}</text>')
        for tick, label in x_ticks:
            x, _ = at(tick, ylo)
            parts.append(f'<text x="{x:.1f}" y="{y0 + h + 14}" text-anchor="middle">{label}</text>')
        for i, (name, (xs, ys)) in enumerate(series.items()):
            colour = COLOURS[i % len(COLOURS)]
            points = " ".join(f"{x:.1f},{y:.1f}" for x, y in (at(a, b) for a, b in zip(xs, ys)))
            parts.append(f'<polyline points="{points}" fill="none" stroke="{colour}" stroke-width="1.8"/>')
            if len(xs) == 1:
                x, y = at(xs[0], ys[0])
                parts.append(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="3" fill="{colour}"/>')
            parts.append(f'<text x="{x0 + w - 4}" y="{y0 + 14 + 13 * i}" text-anchor="end" fill="{colour}" '
                         f'stroke="white" stroke-width="3" paint-order="stroke">{html.escape(name)}</text>')
    parts.append("</svg>")
    return "\n".join(parts)


def training_curve_svg(curve: dict, eval_curve: dict | None = None) -> str:
    """PSNR (training batches, and held-out views when recorded), losses (log scale) and samples
    per ray against the training step, from srf.zarr's `curve` and `eval_curve`."""
    steps = curve.get("step", [])
    psnr = {"training batch": (steps, curve.get("psnr", []))}
    if eval_curve and len(eval_curve.get("step", [])):
        psnr["held-out views"] = (eval_curve["step"], eval_curve.get("psnr", []))
    losses = {name: (steps, curve[name]) for name in ("loss", "photometric", "semantic") if name in curve}
    samples = {label: (steps, curve[name]) for name, label in
               (("samples_per_ray", "evaluated"), ("shaded_per_ray", "shaded")) if name in curve}
    return line_chart_svg([
        {"title": "PSNR (dB)", "series": psnr},
        {"title": "loss", "series": losses, "log": True},
        {"title": "samples per ray", "series": samples},
    ], "training step")


SUMMARY_KEYS = [
    ("psnr", "PSNR (dB)"), ("psnr_object", "PSNR on object pixels (dB)"), ("ssim", "SSIM"),
    ("miou", "mIoU vs the masks (with background)"), ("miou_gt", "mIoU vs ground truth (with background)"),
    ("miou_unlabelled_gt", "mIoU vs ground truth on training views without masks"),
    ("floater_fraction", "floater fraction"), ("samples_skipped_fraction", "samples skipped in empty space"),
    ("samples_per_ray", "samples evaluated per ray"), ("train_seconds", "training seconds"),
    ("views", "held-out views"),
]


def _cell(value) -> str:
    if value is None:
        return "&ndash;"
    if isinstance(value, float):
        return f"{value:.4g}"
    return html.escape(str(value))


def _table(header: list[str], rows: list[list]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_cell(v)}</td>" for v in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def metrics_html(metrics: dict, title: str = "") -> str:
    """A self-contained HTML page of eval/metrics.json: the summary, IoU per class, and per view."""
    sections = [_table(["metric", "value"], [[label, metrics[key]] for key, label in SUMMARY_KEYS if key in metrics])]
    if "iou" in metrics:
        names = list(metrics["iou"])
        rows = [[name, metrics["iou"][name], (metrics.get("iou_gt") or {}).get(name)] for name in names]
        sections.append("<h3>IoU per class</h3>" + _table(["class", "vs the masks", "vs ground truth"], rows))
    views = metrics.get("per_view") or []
    if views:
        columns = [key for key in ("psnr", "psnr_object", "ssim") if key in views[0]]
        sections.append("<h3>Per held-out view</h3>" + _table(["view"] + columns,
                                                              [[v["name"]] + [v.get(k) for k in columns] for v in views]))
    style = ("body{font-family:sans-serif;font-size:13px;margin:8px}table{border-collapse:collapse;margin-bottom:12px}"
             "td,th{border:1px solid #ccc;padding:2px 8px;text-align:left}th{background:#f0f0f0}")
    heading = f"<h2>{html.escape(title)}</h2>" if title else ""
    return (f"<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>{html.escape(title or 'metrics')}</title>"
            f"<style>{style}</style></head><body>{heading}{''.join(sections)}</body></html>\n")
