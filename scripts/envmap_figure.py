"""Draw docs/envmap_convention.svg: the lat-long environment map convention, labelled.

    python scripts/envmap_figure.py [-o docs/envmap_convention.svg]

A 2:1 grid (lines every 30 degrees) with the world direction at each edge and quarter
column (clvol/envmap.py, docs/conventions.md "Environment maps"); the labels are computed
from clvol.envmap.texel_directions, so the picture follows the code.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from clvol.envmap import texel_directions  # noqa: E402

W, H, X0, Y0 = 720, 360, 70, 50          # map size and offset in the picture (pixels)


def axis_name(d) -> str:
    """The world axis a unit vector is closest to, e.g. '-z'."""
    k = int(np.argmax(np.abs(d)))
    return ("+" if d[k] > 0 else "-") + "xyz"[k]


def svg() -> str:
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{W + 2 * X0}" height="{H + 2 * Y0 + 30}" '
           'font-family="sans-serif" font-size="14">',
           f'<rect x="0" y="0" width="{W + 2 * X0}" height="{H + 2 * Y0 + 30}" fill="white"/>']
    # Sky above the horizon, ground below (as examples/sky_64x32.exr), for orientation.
    out.append(f'<rect x="{X0}" y="{Y0}" width="{W}" height="{H // 2}" fill="#cfe0f5"/>')
    out.append(f'<rect x="{X0}" y="{Y0 + H // 2}" width="{W}" height="{H // 2}" fill="#e6dccf"/>')
    for k in range(13):                                  # phi every 30 degrees
        x = X0 + W * k / 12
        out.append(f'<line x1="{x}" y1="{Y0}" x2="{x}" y2="{Y0 + H}" stroke="#888" '
                   f'stroke-width="{2 if k % 3 == 0 else 0.7}"/>')
    for k in range(7):                                   # theta every 30 degrees
        y = Y0 + H * k / 6
        out.append(f'<line x1="{X0}" y1="{y}" x2="{X0 + W}" y2="{y}" stroke="#888" '
                   f'stroke-width="{2 if k % 3 == 0 else 0.7}"/>')
        out.append(f'<text x="{X0 - 8}" y="{y + 5}" text-anchor="end">{30 * k}°</text>')
    # Directions on the horizon at the quarter columns, computed from the convention.
    d = texel_directions(2, 8)[1]   # row just below the horizon, 8 columns: centres at 22.5 + 45 k deg
    for k in range(4):
        # Column boundary k W/4 lies between centres 2k - 1 and 2k: average them.
        a = d[2 * k] + d[(2 * k - 1) % 8]
        x = X0 + W * k / 4
        out.append(f'<text x="{x + 4}" y="{Y0 + H // 2 - 6}" font-weight="bold">'
                   f'{axis_name(a * [1, 0, 1])}</text>')
    out.append(f'<text x="{X0 + W - 4}" y="{Y0 + H // 2 - 6}" text-anchor="end" '
               f'font-weight="bold">+x</text>')
    out.append(f'<text x="{X0 + W / 2}" y="{Y0 - 28}" text-anchor="middle" font-weight="bold">'
               '+y (up): row 0, v = 0</text>')
    out.append(f'<text x="{X0 + W / 2}" y="{Y0 + H + 22}" text-anchor="middle" font-weight="bold">'
               '-y (down): last row, v = 1</text>')
    for k in range(13):
        out.append(f'<text x="{X0 + W * k / 12}" y="{Y0 - 8}" text-anchor="middle" '
                   f'font-size="11">{30 * k}°</text>')
    out.append(f'<text x="{X0 + W / 2}" y="{Y0 + H + 50}" text-anchor="middle">'
               'u = phi / 360°, phi = atan2(-z, x) - rotation: from +x toward -z '
               '(counter-clockwise seen from above); v = theta / 180°, theta = acos(y)</text>')
    out.append(f'<text x="{X0 - 55}" y="{Y0 + H / 2}" transform="rotate(-90 {X0 - 55} '
               f'{Y0 + H / 2})" text-anchor="middle">theta (polar, from +y)</text>')
    out.append("</svg>")
    return "\n".join(out) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", default=str(Path(__file__).resolve().parents[1] / "docs"
                                      / "envmap_convention.svg"))
    out = Path(ap.parse_args().o)
    out.write_text(svg())
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
