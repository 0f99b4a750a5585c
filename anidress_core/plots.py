"""Small inline-SVG charts for the HTML report (no plotting library needed).

Pure functions: data in, an ``<svg>`` string out (sizes in CSS pixels). NaN/inf values
are dropped; an empty chart says so instead of failing. Used by
:mod:`anidress_core.stages.report`.
"""
from __future__ import annotations

import html
import math
from typing import Sequence

__all__ = ["line_chart", "scatter_chart", "bar_chart", "pareto_front"]

PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#7f7f7f")


def _finite(xs: Sequence[float], ys: Sequence[float]) -> list[tuple[float, float]]:
    return [(float(x), float(y)) for x, y in zip(xs, ys)
            if x is not None and y is not None and math.isfinite(float(x)) and math.isfinite(float(y))]


def _ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """About ``n`` round tick values covering [lo, hi]."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo]
    raw = (hi - lo) / max(1, n)
    mag = 10 ** math.floor(math.log10(raw))
    step = min((m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=raw)
    start = math.ceil(lo / step) * step
    out, v = [], start
    while v <= hi + 1e-9 * step and len(out) < 50:
        out.append(round(v, 12))
        v += step
    return out


def _fmt(v: float) -> str:
    if v == 0:
        return "0"
    a = abs(v)
    if a >= 1e4 or a < 1e-3:
        return f"{v:.1e}"
    return f"{v:.4g}"


class _Frame:
    """Axes geometry shared by the charts (linear or log10 axes)."""

    def __init__(self, pts, width, height, logx=False, logy=False, y0=None):
        self.w, self.h = width, height
        self.ml, self.mr, self.mt, self.mb = 64, 16, 28, 44
        self.logx, self.logy = logx, logy
        xs = [self._tx(p[0]) for p in pts]
        ys = [self._ty(p[1]) for p in pts]
        if y0 is not None:
            ys.append(self._ty(y0))
        self.x0, self.x1 = (min(xs), max(xs)) if xs else (0.0, 1.0)
        self.y0, self.y1 = (min(ys), max(ys)) if ys else (0.0, 1.0)
        for a in ("x", "y"):
            lo, hi = getattr(self, a + "0"), getattr(self, a + "1")
            if hi - lo <= 1e-12 * max(1.0, abs(hi)):
                lo, hi = lo - 0.5 * max(1.0, abs(lo)) * 0.1, hi + 0.5 * max(1.0, abs(hi)) * 0.1
            pad = 0.05 * (hi - lo)
            setattr(self, a + "0", lo - pad)
            setattr(self, a + "1", hi + pad)

    def _tx(self, x):
        return math.log10(x) if self.logx else x

    def _ty(self, y):
        return math.log10(y) if self.logy else y

    def px(self, x):
        return self.ml + (self._tx(x) - self.x0) / (self.x1 - self.x0) * (self.w - self.ml - self.mr)

    def py(self, y):
        return self.h - self.mb - (self._ty(y) - self.y0) / (self.y1 - self.y0) * (self.h - self.mt - self.mb)

    def axes(self, title, xlabel, ylabel) -> list[str]:
        out = [f'<rect x="{self.ml}" y="{self.mt}" width="{self.w - self.ml - self.mr}" '
               f'height="{self.h - self.mt - self.mb}" fill="none" stroke="#999"/>',
               f'<text x="{self.w / 2:.1f}" y="16" text-anchor="middle" font-weight="bold">{html.escape(title)}</text>',
               f'<text x="{(self.ml + self.w - self.mr) / 2:.1f}" y="{self.h - 6}" text-anchor="middle">'
               f'{html.escape(xlabel)}</text>',
               f'<text transform="translate(14,{(self.mt + self.h - self.mb) / 2:.1f}) rotate(-90)" '
               f'text-anchor="middle">{html.escape(ylabel)}</text>']
        for v in _ticks(self.x0, self.x1):
            val = 10 ** v if self.logx else v
            x = self.ml + (v - self.x0) / (self.x1 - self.x0) * (self.w - self.ml - self.mr)
            out.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{self.h - self.mb}" y2="{self.h - self.mb + 4}" '
                       f'stroke="#999"/><text x="{x:.1f}" y="{self.h - self.mb + 16}" text-anchor="middle">'
                       f'{_fmt(val)}</text>')
        for v in _ticks(self.y0, self.y1):
            val = 10 ** v if self.logy else v
            y = self.h - self.mb - (v - self.y0) / (self.y1 - self.y0) * (self.h - self.mt - self.mb)
            out.append(f'<line x1="{self.ml - 4}" x2="{self.w - self.mr}" y1="{y:.1f}" y2="{y:.1f}" '
                       f'stroke="#eee"/><text x="{self.ml - 6}" y="{y + 4:.1f}" text-anchor="end">{_fmt(val)}</text>')
        return out


def _svg(width, height, body: list[str]) -> str:
    return (f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
            f'viewBox="0 0 {width} {height}" font-family="sans-serif" font-size="11">' + "".join(body) + "</svg>")


def _empty(title, width, height) -> str:
    return _svg(width, height, [f'<text x="{width / 2}" y="{height / 2}" text-anchor="middle" fill="#888">'
                                f'{html.escape(title)}: no data</text>'])


def _legend(labels, width, top=30) -> list[str]:
    out = []
    for i, lab in enumerate(labels):
        y = top + 14 * i
        c = PALETTE[i % len(PALETTE)]
        out.append(f'<rect x="{width - 190}" y="{y - 8}" width="10" height="10" fill="{c}"/>'
                   f'<text x="{width - 175}" y="{y + 1}">{html.escape(str(lab))[:28]}</text>')
    return out


def line_chart(series: Sequence[tuple[str, Sequence[float], Sequence[float]]], title: str, xlabel: str,
               ylabel: str, width: int = 640, height: int = 280, logy: bool = False) -> str:
    """Lines, one per ``(label, xs, ys)``."""
    clean = [(lab, _finite(xs, ys)) for lab, xs, ys in series]
    if logy:
        clean = [(lab, [p for p in pts if p[1] > 0]) for lab, pts in clean]
    clean = [(lab, pts) for lab, pts in clean if pts]
    if not clean:
        return _empty(title, width, height)
    fr = _Frame([p for _, pts in clean for p in pts], width, height, logy=logy)
    body = fr.axes(title, xlabel, ylabel)
    for i, (lab, pts) in enumerate(clean):
        c = PALETTE[i % len(PALETTE)]
        d = " ".join(f"{'M' if j == 0 else 'L'}{fr.px(x):.1f},{fr.py(y):.1f}" for j, (x, y) in enumerate(pts))
        body.append(f'<path d="{d}" fill="none" stroke="{c}" stroke-width="1.5"><title>{html.escape(lab)}</title></path>')
    if len(clean) > 1:
        body += _legend([lab for lab, _ in clean], width)
    return _svg(width, height, body)


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats in both coordinates (lower is better)."""
    idx = []
    for i, (xi, yi) in enumerate(points):
        dominated = any((xj <= xi and yj <= yi) and (xj < xi or yj < yi) for j, (xj, yj) in enumerate(points) if j != i)
        if not dominated:
            idx.append(i)
    return sorted(idx, key=lambda i: points[i][0])


def scatter_chart(points: Sequence[dict], title: str, xlabel: str, ylabel: str, width: int = 640, height: int = 300,
                  logx: bool = True, front: bool = True) -> str:
    """Points ``{"x", "y", "label", "group", "highlight"}``; lower-left is better.

    ``front``: the Pareto front (per chart) drawn as a step line; highlighted points
    (the config's defaults) are drawn larger with a black outline.
    """
    pts = [p for p in points if p.get("x") is not None and p.get("y") is not None
           and math.isfinite(p["x"]) and math.isfinite(p["y"]) and (p["x"] > 0 or not logx)]
    if not pts:
        return _empty(title, width, height)
    fr = _Frame([(p["x"], p["y"]) for p in pts], width, height, logx=logx)
    body = fr.axes(title, xlabel, ylabel)
    groups = list(dict.fromkeys(p.get("group", "") for p in pts))
    if front and len(pts) > 1:
        fi = pareto_front([(p["x"], p["y"]) for p in pts])
        d, prev = [], None
        for j, i in enumerate(fi):
            x, y = fr.px(pts[i]["x"]), fr.py(pts[i]["y"])
            d.append(f"M{x:.1f},{y:.1f}" if prev is None else f"L{x:.1f},{prev[1]:.1f} L{x:.1f},{y:.1f}")
            prev = (x, y)
        body.append(f'<path d="{" ".join(d)}" fill="none" stroke="#555" stroke-dasharray="4,3"/>')
    for p in pts:
        c = PALETTE[groups.index(p.get("group", "")) % len(PALETTE)]
        r, stroke = (6, ' stroke="#000" stroke-width="2"') if p.get("highlight") else (4, "")
        body.append(f'<circle cx="{fr.px(p["x"]):.1f}" cy="{fr.py(p["y"]):.1f}" r="{r}" fill="{c}"{stroke}>'
                    f'<title>{html.escape(str(p.get("label", "")))}</title></circle>')
    if len(groups) > 1 or groups[0]:
        body += _legend(groups, width)
    return _svg(width, height, body)


def bar_chart(items: Sequence[tuple[str, float]], title: str, xlabel: str, width: int = 640,
              bar: int = 16) -> str:
    """Horizontal bars ``(label, value)``, largest first."""
    items = [(lab, float(v)) for lab, v in items if v is not None and math.isfinite(float(v))]
    if not items:
        return _empty(title, width, 80)
    items.sort(key=lambda t: -t[1])
    left, top = 190, 28
    height = top + bar * len(items) + 30
    vmax = max(v for _, v in items) or 1.0
    body = [f'<text x="{width / 2:.1f}" y="16" text-anchor="middle" font-weight="bold">{html.escape(title)}</text>']
    for i, (lab, v) in enumerate(items):
        y = top + i * bar
        w = (width - left - 70) * v / vmax
        body.append(f'<text x="{left - 6}" y="{y + bar - 5}" text-anchor="end">{html.escape(lab)[:32]}</text>'
                    f'<rect x="{left}" y="{y + 2}" width="{max(w, 0.5):.1f}" height="{bar - 4}" fill="{PALETTE[0]}"/>'
                    f'<text x="{left + w + 4:.1f}" y="{y + bar - 5}">{_fmt(v)}</text>')
    body.append(f'<text x="{(left + width) / 2:.1f}" y="{height - 8}" text-anchor="middle">{html.escape(xlabel)}</text>')
    return _svg(width, height, body)
