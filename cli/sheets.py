"""PNG contact sheets: images side by side, each upscaled (nearest) to a common height so pixels stay visible."""

from __future__ import annotations

from pathlib import Path

from ..fileio import atomic_write


def contact_sheet(paths: list, out: Path, columns: int, height: int = 192, pad: int = 4) -> Path:
    from PIL import Image

    ims = []
    for p in paths:
        im = Image.open(p).convert("RGB")
        w = max(1, round(im.width * height / im.height))
        ims.append(im.resize((w, height), Image.Resampling.NEAREST))
    rows = [ims[i:i + columns] for i in range(0, len(ims), columns)]
    W = max(sum(i.width for i in r) + pad * (len(r) + 1) for r in rows)
    H = len(rows) * (height + pad) + pad
    sheet = Image.new("RGB", (W, H), (255, 255, 255))
    y = pad
    for r in rows:
        x = pad
        for im in r:
            sheet.paste(im, (x, y))
            x += im.width + pad
        y += height + pad
    with atomic_write(out) as fh:
        sheet.save(fh, format="PNG")
    return out
