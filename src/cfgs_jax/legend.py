"""The legend drawn under each rendered view: date names in their highlight colours."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from cfgs_jax import viz


def legend_strip(names: list[str], t, width: int, *, highlight: bool, stops=viz.DEFAULT_STOPS) -> np.ndarray:
    """[h, width, 3] sRGB strip: the date names coloured by their highlight colour (white for plain
    blends); unselected dates grey and struck through."""

    font = ImageFont.load_default()
    height = 16
    img = Image.new("RGB", (width, height), (24, 24, 24))
    draw = ImageDraw.Draw(img)
    cols = viz.date_colours(len(names), stops) if highlight else np.ones((len(names), 3))
    x = 4
    for name, sel, c in zip(names, np.asarray(t), cols):
        fill = tuple(int(round(255 * v)) for v in (c if sel else (0.45, 0.45, 0.45)))
        box = (x, 4, x + 8, 12)
        draw.rectangle(box, fill=fill if sel else None, outline=fill)
        x += 12
        draw.text((x, 2), name, fill=fill, font=font)
        w = draw.textlength(name, font=font)
        if not sel:
            draw.line((x, height // 2, x + w, height // 2), fill=fill, width=1)
        x += int(w) + 10
    return np.asarray(img, np.float32) / 255.0
