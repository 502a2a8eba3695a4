"""Small PNG charts with Pillow (no plotting library needed): x–y series with a legend."""

from __future__ import annotations

import math

import numpy as np

from ._io import atomic_write

_COLOURS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
            (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]


def _ticks(low: float, high: float, log: bool) -> list[float]:
    if log:
        return [10.0**e for e in range(math.floor(math.log10(low)), math.ceil(math.log10(high)) + 1)]
    span = high - low or 1.0
    step = 10 ** math.floor(math.log10(span / 4))
    step *= next(m for m in (1, 2, 5, 10) if span / (step * m) <= 6)
    return list(np.arange(math.ceil(low / step) * step, high + step / 2, step))


def line_chart(path, series: dict[str, tuple], title: str, x_label: str, y_label: str,
               log_x: bool = False, size=(900, 560), markers: bool = True) -> None:
    """Write a chart of ``{name: (x, y)}`` series to a PNG (atomically)."""
    from PIL import Image, ImageDraw

    width, height = size
    left, right, top, bottom = 80, 230, 40, 60
    xs = np.concatenate([np.asarray(x, float) for x, _ in series.values()])
    ys = np.concatenate([np.asarray(y, float) for _, y in series.values()])
    finite = np.isfinite(xs) & np.isfinite(ys) & ((xs > 0) if log_x else True)
    x_low, x_high = xs[finite].min(), xs[finite].max()
    y_low, y_high = ys[finite].min(), ys[finite].max()
    if log_x:
        x_low, x_high = 10 ** math.floor(math.log10(x_low) * 4) / 4, x_high * 1.2
    pad = (y_high - y_low) * 0.05 or 0.01
    y_low, y_high = y_low - pad, y_high + pad

    def to_px(x, y):
        fx = (math.log10(x) - math.log10(x_low)) / (math.log10(x_high) - math.log10(x_low)) if log_x \
            else (x - x_low) / ((x_high - x_low) or 1.0)
        fy = (y - y_low) / ((y_high - y_low) or 1.0)
        return left + fx * (width - left - right), height - bottom - fy * (height - top - bottom)

    image = Image.new("RGB", size, "white")
    draw = ImageDraw.Draw(image)
    draw.rectangle([left, top, width - right, height - bottom], outline="black")
    for tick in _ticks(x_low, x_high, log_x):
        if x_low <= tick <= x_high:
            px, _ = to_px(tick, y_low)
            draw.line([px, top, px, height - bottom], fill=(225, 225, 225))
            draw.text((px - 12, height - bottom + 6), f"{tick:g}", fill="black")
    for tick in _ticks(y_low, y_high, False):
        _, py = to_px(x_low, tick)
        draw.line([left, py, width - right, py], fill=(225, 225, 225))
        draw.text((8, py - 6), f"{tick:.4g}", fill="black")
    for index, (name, (x, y)) in enumerate(series.items()):
        colour = _COLOURS[index % len(_COLOURS)]
        points = [to_px(a, b) for a, b in zip(x, y) if np.isfinite(a) and np.isfinite(b) and (a > 0 or not log_x)]
        if len(points) > 1:
            draw.line(points, fill=colour, width=2)
        if markers:
            for px, py in points:
                draw.ellipse([px - 3, py - 3, px + 3, py + 3], fill=colour)
        ly = top + 16 * index
        draw.rectangle([width - right + 12, ly + 2, width - right + 24, ly + 12], fill=colour)
        draw.text((width - right + 30, ly), name[:30], fill="black")
    draw.text((left, 12), title, fill="black")
    draw.text(((width - right + left) // 2 - 60, height - 24), x_label + (" (log)" if log_x else ""), fill="black")
    draw.text((8, top - 24), y_label, fill="black")
    with atomic_write(path) as handle:
        image.save(handle, format="PNG")
