"""Render PNG screenshots of the two models' HTML animations for the README.

Each model is simulated (closedchain.simulate, from its assembled reference
configuration under gravity, no torque), written as an HTML animation, opened
in Debian's headless Chromium (Playwright, every network request aborted),
paused at a fixed time with meshcat's time scrubber, and captured. The PNG is
reduced to a palette to keep it small.

Run:  python scripts/screenshot.py   (writes docs/img/fourbar.png, docs/img/agile_eye.png)
Needs Debian's ``chromium`` and the ``playwright`` Python package (no
``playwright install``).
"""

from __future__ import annotations

import argparse
import io
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image
from playwright.sync_api import sync_playwright

import closedchain as cc
from closedchain.simulate import simulate
from closedchain.visualize import CHROMIUM_PATH, HEADLESS_CHROMIUM_ARGS, AnimationSettings

ROOT = Path(__file__).resolve().parent.parent

#: model -> (simulated duration [s], time of the screenshot [s]).
SHOTS = {
    "fourbar": (2.0, 0.25),  # mid-swing (the crank swings towards its change point)
    "agile_eye": (1.0, 0.5),
}
#: Time for a page to load and render [ms].
LOAD_TIMEOUT_MS = 60_000
#: Display rate of the animations [frames/s].
FPS = 30.0


def render(browser, html: Path, t: float, size: tuple[int, int]) -> bytes:
    """Open the page offline, pause it at time t [s] and return a PNG screenshot."""
    url = html.resolve().as_uri()
    context = browser.new_context(viewport={"width": size[0], "height": size[1]})
    page = context.new_page()
    page.route(
        "**/*", lambda route: route.continue_() if route.request.url == url else route.abort()
    )
    page.goto(url)
    page.wait_for_function(
        "() => window.closedchain && window.closedchain.ready", timeout=LOAD_TIMEOUT_MS
    )
    page.evaluate(
        "(t) => { const a = window.closedchain.viewer.animator;"
        " a.pause(); a.time_scrubber.setValue(t); }",
        t,
    )
    page.wait_for_timeout(300)
    png = page.screenshot()
    context.close()
    return png


def shrink(png: bytes, colors: int) -> bytes:
    """Reduce a PNG to a palette of ``colors`` colours."""
    img = Image.open(io.BytesIO(png)).convert("RGB")
    out = io.BytesIO()
    img.quantize(colors=colors, method=Image.Quantize.FASTOCTREE).save(out, "PNG", optimize=True)
    return out.getvalue()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", type=Path, default=ROOT / "docs" / "img")
    parser.add_argument("--size", type=int, nargs=2, default=(720, 420), metavar=("W", "H"))
    parser.add_argument("--colors", type=int, default=256, help="palette size of the PNGs")
    args = parser.parse_args(argv)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    settings = AnimationSettings(open_controls=False)
    with tempfile.TemporaryDirectory() as tmp, sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=CHROMIUM_PATH, args=list(HEADLESS_CHROMIUM_ARGS), headless=True
        )
        for name, (t_final, t_shot) in SHOTS.items():
            mech = cc.load(ROOT / "models" / f"{name}.urdf")
            n = int(round(t_final * FPS)) + 1
            traj = simulate(
                mech,
                mech.q_ref,
                np.zeros(mech.nv),
                t_final,
                t_eval=np.linspace(0, t_final, n),
                method="kkt",
                integrator="DOP853",
            )
            html = cc.write_html(mech, traj, Path(tmp) / f"{name}.html", fps=FPS, settings=settings)
            png = shrink(render(browser, html.path, t_shot, tuple(args.size)), args.colors)
            out = args.out_dir / f"{name}.png"
            out.write_bytes(png)
            print(f"wrote {out} ({len(png) / 1024:.0f} kB; animation {html.size / 1e6:.2f} MB)")
        browser.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
