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


def _axis_range(values: np.ndarray, log: bool) -> tuple[float, float]:
    low, high = float(values.min()), float(values.max())
    if log:
        return 10 ** math.floor(math.log10(low)), 10 ** math.ceil(math.log10(high))
    pad = (high - low) * 0.05 or 0.01
    return low - pad, high + pad


def line_chart(path, series: dict[str, tuple], title: str, x_label: str, y_label: str,
               log_x: bool = False, log_y: bool = False, size=(900, 560), connect: bool = True,
               point_labels: dict[str, list[str]] | None = None) -> None:
    """Write a chart of ``{name: (x, y)}`` series to a PNG (atomically).

    ``connect=False`` draws points only; ``point_labels`` names each point of
    a series; log axes need positive values (others are left out).
    """
    from PIL import Image, ImageDraw

    width, height = size
    left, right, top, bottom = 80, 230, 50, 60
    xs = np.concatenate([np.asarray(x, float) for x, _ in series.values()])
    ys = np.concatenate([np.asarray(y, float) for _, y in series.values()])

    def shown(x, y):
        return np.isfinite(x) and np.isfinite(y) and (x > 0 or not log_x) and (y > 0 or not log_y)

    keep = np.array([shown(a, b) for a, b in zip(xs, ys)])
    x_low, x_high = _axis_range(xs[keep], log_x)
    y_low, y_high = _axis_range(ys[keep], log_y)

    def fraction(value, low, high, log):
        if log:
            return (math.log10(value) - math.log10(low)) / (math.log10(high) - math.log10(low))
        return (value - low) / ((high - low) or 1.0)

    def to_px(x, y):
        fx, fy = fraction(x, x_low, x_high, log_x), fraction(y, y_low, y_high, log_y)
        return left + fx * (width - left - right), height - bottom - fy * (height - top - bottom)

    image = Image.new("RGB", size, "white")
    draw = ImageDraw.Draw(image)
    draw.rectangle([left, top, width - right, height - bottom], outline="black")
    for tick in _ticks(x_low, x_high, log_x):
        if x_low <= tick <= x_high:
            px, _ = to_px(tick, y_low)
            draw.line([px, top, px, height - bottom], fill=(225, 225, 225))
            draw.text((px - 12, height - bottom + 6), f"{tick:g}", fill="black")
    for tick in _ticks(y_low, y_high, log_y):
        if y_low <= tick <= y_high:
            _, py = to_px(x_low, tick)
            draw.line([left, py, width - right, py], fill=(225, 225, 225))
            draw.text((8, py - 6), f"{tick:.4g}", fill="black")
    for index, (name, (x, y)) in enumerate(series.items()):
        colour = _COLOURS[index % len(_COLOURS)]
        labels = (point_labels or {}).get(name, [""] * len(x))
        points = [(to_px(a, b), label) for a, b, label in zip(x, y, labels) if shown(a, b)]
        if connect and len(points) > 1:
            draw.line([p for p, _ in points], fill=colour, width=2)
        for (px, py), label in points:
            draw.ellipse([px - 3, py - 3, px + 3, py + 3], fill=colour)
            if label:
                draw.text((px + 5, py - 5), label, fill=colour)
        ly = top + 16 * index
        draw.rectangle([width - right + 12, ly + 2, width - right + 24, ly + 12], fill=colour)
        draw.text((width - right + 30, ly), name[:30], fill="black")
    draw.text((left, 8), title, fill="black")
    draw.text(((width - right + left) // 2 - 60, height - 24), x_label + (" (log)" if log_x else ""), fill="black")
    draw.text((left, top - 18), y_label + (" (log)" if log_y else ""), fill="black")
    with atomic_write(path) as handle:
        image.save(handle, format="PNG")
