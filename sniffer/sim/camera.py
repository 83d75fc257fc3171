"""The simulated camera: a small JPEG test picture with a frame counter.

A generated picture rather than shipped files so that consecutive frames differ
visibly (counter, clock, a marker sweeping across) and a viewer of a recording can
tell frames apart and see them advance.
"""

from __future__ import annotations

import io
from functools import cache

from PIL import Image, ImageDraw, ImageFont

WIDTH, HEIGHT = 160, 120
QUALITY = 80
_BARS = ((192, 192, 192), (192, 192, 0), (0, 192, 192), (0, 192, 0),
         (192, 0, 192), (192, 0, 0), (0, 0, 192))


@cache
def _font(size: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    try:
        return ImageFont.load_default(size=size)
    except (AttributeError, ImportError, OSError):  # Pillow without FreeType: fixed bitmap font
        return ImageFont.load_default()


def render_frame(frame: int, t_s: float) -> bytes:
    """JPEG bytes of frame number ``frame`` taken ``t_s`` seconds after start."""
    image = Image.new("RGB", (WIDTH, HEIGHT), (16, 16, 16))
    draw = ImageDraw.Draw(image)
    bar = WIDTH // len(_BARS)
    for i, colour in enumerate(_BARS):
        draw.rectangle((i * bar, 0, (i + 1) * bar - 1, 59), fill=colour)
    x = round((t_s * 40) % (WIDTH - 12))
    draw.rectangle((x, 62, x + 11, 73), fill=(255, 255, 255))
    draw.text((6, 78), f"frame {frame:06d}", font=_font(18), fill=(255, 255, 255))
    draw.text((6, 100), f"t = {t_s:9.2f} s  whiztap sim", font=_font(11), fill=(160, 160, 160))
    out = io.BytesIO()
    image.save(out, "JPEG", quality=QUALITY)
    return out.getvalue()
