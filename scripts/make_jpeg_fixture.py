"""Writes the JPEG decoder fixtures of crates/data/tests/image_jpeg.rs (run once; needs Pillow).

Three 48x32 JPEGs of the same smooth colour pattern, encoded by libjpeg through Pillow: `pattern_444.jpg`
(quality 95, no chroma subsampling), `pattern_420.jpg` (quality 90, 4:2:0 like nuScenes camera
images) and `pattern_420_progressive.jpg` (the same, progressive: several scans with tables between
them), each with libjpeg's own RGB decoding next to it as raw bytes (`*.rgb`, row-major, 3 bytes per
pixel), the reference the Rust decoder is compared with.

    python scripts/make_jpeg_fixture.py crates/data/tests/data
"""
import sys
from pathlib import Path

from PIL import Image

out = Path(sys.argv[1])
out.mkdir(parents=True, exist_ok=True)
w, h = 48, 32
img = Image.new("RGB", (w, h))
img.putdata(
    [
        (
            (8 * x + 3 * y) % 256,
            (255 - 6 * y + 2 * x) % 256,
            (128 + 40 * ((x // 8 + y // 8) % 2) + x) % 256,
        )
        for y in range(h)
        for x in range(w)
    ]
)
for name, quality, subsampling, progressive in [
    ("pattern_444", 95, 0, False),
    ("pattern_420", 90, 2, False),
    ("pattern_420_progressive", 90, 2, True),
]:
    jpg = out / f"{name}.jpg"
    img.save(jpg, "JPEG", quality=quality, subsampling=subsampling, progressive=progressive)
    decoded = Image.open(jpg).convert("RGB")
    (out / f"{name}.rgb").write_bytes(decoded.tobytes())
    print(jpg, jpg.stat().st_size, "bytes")
