#!/usr/bin/env python
"""Peak memory of reading the largest input each reader accepts (docs/robustness.md).

Each case writes its file at the reader's size limit, then reads it in a new
Python process that first imports what it needs; the figure is how far the
process's peak resident memory (VmHWM, reset before the read) rises above
the memory resident before the read, so that Pillow's and NumPy's own
allocations count too (tracemalloc sees only Python's). Linux only. Cases:

- a phantom file of exactly ``max_scatterers·MAX_ROW_BYTES`` bytes (300,000
  rows padded to 256 bytes), by the fast reader and by the line-by-line
  reader (a bad last value sends the file there; it is then refused);
- a PNG of :data:`octcl._io.MAX_IMAGE_PIXELS` (4096x4096 grey RGBA) read
  without a shape (``read_png_pixels``, and ``octcl maps``' whole
  computation, :func:`octcl.maps.write_maps`);
- a B-scan PNG (256x512) read as a target, for scale;
- a ``.npy`` of :data:`octcl._io.MAX_IMAGE_FILE_BYTES` less its header, read
  and refused as no B-scan (``decode_scan_levels``).

    python scripts/bench_limits.py
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from octcl._io import MAX_IMAGE_FILE_BYTES, MAX_IMAGE_PIXELS, write_grey_png
from octcl.config import DEFAULT_CONFIG
from octcl.phantom import MAX_ROW_BYTES

#: Imports, then the peak resident memory reset (Linux: 5 to /proc/self/clear_refs), the
#: read, and the peak's growth over the memory resident before it, in bytes.
_MEASURE = """
import sys
{imports}

def kib(field):
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith(field + ":"))

path = sys.argv[1]
with open("/proc/self/clear_refs", "w") as clear:
    clear.write("5")
before = kib("VmRSS")
try:
    {read}
except ValueError:
    pass
print((kib("VmHWM") - before) * 1024)
"""


def peak_growth(path: Path, imports: str, read: str) -> int:
    code = _MEASURE.format(imports=imports, read=read)
    result = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, check=True)
    return int(result.stdout.split()[-1])


def main() -> None:
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
          f"NumPy {np.__version__}")
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        phantom = folder / "largest.txt"
        row = b"1.00000e+00 2.00000e+00 3.00000e+00 4.00000e+00"
        padded = row + b" " * (MAX_ROW_BYTES - len(row) - 1) + b"\n"
        load = ("from octcl.phantom import Phantom", "Phantom.load(path)")
        phantom.write_bytes(padded * DEFAULT_CONFIG.max_scatterers)
        rows.append(("phantom, fast reader", phantom, *load))
        bad = folder / "largest_bad.txt"
        bad.write_bytes(padded * (DEFAULT_CONFIG.max_scatterers - 1) + padded.replace(b"4.00000e+00", b"-1"))
        rows.append(("phantom, line-by-line reader (refused at the last row)", bad, *load))
        image = folder / "largest.png"
        levels = np.random.default_rng(0).integers(0, 256, (4096, MAX_IMAGE_PIXELS // 4096), dtype=np.uint8)
        write_grey_png(image, levels)
        rows.append(("PNG of MAX_IMAGE_PIXELS, read_png_pixels", image,
                     "from octcl._io import read_png_pixels", "read_png_pixels(path)"))
        rows.append(("PNG of MAX_IMAGE_PIXELS, octcl maps (write_maps)", image,
                     "from octcl.maps import write_maps", "write_maps(path, path + '.maps')"))
        scan = folder / "scan.png"
        write_grey_png(scan, levels[:256, :512])
        rows.append(("B-scan PNG 256x512, read_target", scan,
                     "from octcl.host.pipeline.target import read_target", "read_target(path)"))
        npy = folder / "largest.npy"
        side = int((MAX_IMAGE_FILE_BYTES - 128) ** 0.5)
        np.save(npy, np.zeros((side, side), np.uint8))
        rows.append((f".npy of {npy.stat().st_size:,} bytes, decode_scan_levels (refused: not 256x512)", npy,
                     "from octcl._io import decode_scan_levels, read_image_bytes",
                     "decode_scan_levels(read_image_bytes(path), (256, 512), path)"))
        print("\n| input | file MB | peak memory growth MB | growth / file size |\n|---|---|---|---|")
        for label, path, imports, read in rows:
            size = path.stat().st_size
            growth = peak_growth(path, imports, read)
            print(f"| {label} | {size / 1e6:.1f} | {growth / 1e6:.0f} | {growth / size:.1f} |", flush=True)


if __name__ == "__main__":
    main()
