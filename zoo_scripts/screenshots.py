"""Screenshots of what a newcomer sees, at 1280 px wide: the README rendered as HTML and the labelling page.

    python zoo_scripts/screenshots.py           # or `make screenshots`

Writes ``docs/_static/screenshots/readme.png`` and ``labelling-page.png`` (whole pages, 1280 px wide) and
``screenshots.json``, the fingerprint of what each one shows. ``tests/tools/test_screenshots.py`` compares those fingerprints
with the sources, without a browser: a screenshot whose source changed in a way that changes how it looks fails the
test until this script is run again.

- The README's fingerprint is its outline (:func:`readme_outline`): headings, table header rows, images and code
  fences. Its wording and numbers change often (``zoo_scripts/report.py --write`` rewrites the results),
  and a screenshot of every such edit would add a binary file to the history each time without changing the layout
  it shows.
- The labelling page's fingerprint is its HTML (:data:`sb3_dipper.labelling.app.PAGE`) and the module that draws its
  pictures (``sb3_dipper/labelling/render.py``), exactly: they change seldom, and any change can change the page.

Needs the system's Chromium and chromedriver (``apt-get install chromium chromium-driver``, as ``make test`` does),
selenium (the ``tests`` extra), markdown (the ``docs`` extra) and the labelling page's packages (the ``label`` extra).
The labelling page shows the queue of a tiny DIPPER run on the four-room maze (seed 0): early, untrained pairs.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import io
import json
import logging
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
SCREENSHOTS = REPO / "docs" / "_static" / "screenshots"
FINGERPRINTS = SCREENSHOTS / "screenshots.json"
README_PNG = "readme.png"
PAGE_PNG = "labelling-page.png"
WIDTH = 1280
# The browser window's height while the page lays out; the screenshot then covers the whole page.
VIEWPORT_HEIGHT = 900
PAGE_SOURCES = ("sb3_dipper/labelling/app.py:PAGE", "sb3_dipper/labelling/render.py")

# The README as GitHub shows it on a wide screen: its Markdown body at most 980 px wide, GitHub's fonts and tables.
README_STYLE = """
body { margin: 0; background: #fff; }
.markdown-body { box-sizing: border-box; max-width: 980px; margin: 0 auto; padding: 45px;
  font-family: -apple-system, "Segoe UI", "Noto Sans", Helvetica, Arial, sans-serif; font-size: 16px;
  line-height: 1.5; color: #1f2328; }
h1, h2 { border-bottom: 1px solid #d1d9e0; padding-bottom: .3em; }
h1 { font-size: 2em; } h2 { font-size: 1.5em; margin-top: 24px; }
a { color: #0969da; text-decoration: none; }
code { font-family: ui-monospace, "DejaVu Sans Mono", monospace; font-size: 85%; background: #eff1f3;
  padding: .2em .4em; border-radius: 6px; }
pre { background: #f6f8fa; padding: 16px; border-radius: 6px; overflow: auto; line-height: 1.45; }
pre code { background: none; padding: 0; font-size: 85%; }
table { border-collapse: collapse; display: block; width: max-content; max-width: 100%; overflow: auto;
  margin: 0 0 16px; }
th, td { border: 1px solid #d1d9e0; padding: 6px 13px; }
th { font-weight: 600; } tr:nth-child(2n) { background: #f6f8fa; }
img { max-width: 100%; }
"""


def readme_outline(text: str) -> list[str]:
    """What the README's layout is made of: its headings, table header rows, images and code fences (their languages).

    Lines inside code blocks are content, even those that start with ``#``.
    """
    outline = []
    in_code = False
    previous = ""
    for line in text.splitlines():
        if line.startswith("```"):
            in_code = not in_code
            outline.append(line)
        elif not in_code and (line.startswith("#") or "![" in line or (line.startswith("|") and not previous.startswith("|"))):
            outline.append(line)
        previous = line
    return outline


def page_source() -> str:
    """The labelling page's HTML and the source of the module that draws its pictures."""
    from sb3_dipper.labelling.app import PAGE

    return PAGE + (REPO / "sb3_dipper" / "labelling" / "render.py").read_text(encoding="utf-8")


def fingerprints() -> dict[str, dict[str, Any]]:
    """For each screenshot: the sources it shows and the sha256 of what of them it depends on."""
    outline = "\n".join(readme_outline((REPO / "README.md").read_text(encoding="utf-8")))
    return {
        README_PNG: {"sources": ["README.md (its outline)"], "sha256": hashlib.sha256(outline.encode()).hexdigest()},
        PAGE_PNG: {"sources": list(PAGE_SOURCES), "sha256": hashlib.sha256(page_source().encode()).hexdigest()},
    }


def readme_html() -> str:
    """The README as HTML, its relative links and images resolved against the checkout."""
    import markdown

    body = markdown.markdown((REPO / "README.md").read_text(encoding="utf-8"), extensions=["tables", "fenced_code"])
    return (
        f'<!doctype html><html><head><meta charset="utf-8"><base href="{REPO.as_uri()}/">'
        f'<style>{README_STYLE}</style></head><body><article class="markdown-body">{body}</article></body></html>'
    )


def start_chromium() -> Any:
    """Headless Chromium through chromedriver, its viewport ``WIDTH`` CSS pixels wide at one device pixel each."""
    from selenium import webdriver

    binary, driver = shutil.which("chromium"), shutil.which("chromedriver")
    if binary is None or driver is None:
        sys.exit("Screenshots need chromium and chromedriver: apt-get install chromium chromium-driver")
    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--hide-scrollbars"):
        options.add_argument(argument)
    options.add_argument(f"--window-size={WIDTH},{VIEWPORT_HEIGHT}")
    browser = webdriver.Chrome(options=options, service=webdriver.ChromeService(executable_path=driver))
    metrics = {"width": WIDTH, "height": VIEWPORT_HEIGHT, "deviceScaleFactor": 1, "mobile": False}
    browser.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", metrics)
    return browser


def wait_for(condition: Any, what: str, seconds: float = 60.0) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > deadline:
            sys.exit(f"Gave up after {seconds:.0f} s waiting for {what}")
        time.sleep(0.2)


def whole_page_png(browser: Any) -> bytes:
    """The whole page, ``WIDTH`` px wide and as tall as its content, once every image on it has loaded.

    Stored in 256 colours: a third of the size of Chromium's full-colour PNG with no visible loss on text and figures,
    and each regeneration adds the files to the repository's history.
    """
    from PIL import Image

    loaded = "return Array.from(document.images).every(image => image.complete && image.naturalWidth > 0)"
    wait_for(lambda: browser.execute_script(loaded), "the page's images")
    height = math.ceil(browser.execute_cdp_cmd("Page.getLayoutMetrics", {})["cssContentSize"]["height"])
    clip = {"x": 0, "y": 0, "width": WIDTH, "height": height, "scale": 1}
    shot = browser.execute_cdp_cmd("Page.captureScreenshot", {"format": "png", "captureBeyondViewport": True, "clip": clip})
    image = Image.open(io.BytesIO(base64.b64decode(shot["data"]))).convert("RGB")
    palette = image.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    buffer = io.BytesIO()
    palette.save(buffer, format="png", optimize=True)
    return buffer.getvalue()


def queue_of_a_tiny_run(directory: Path) -> None:
    """Four pairs queued for people by a tiny DIPPER run on the four-room maze."""
    import torch as th
    from stable_baselines3.common.env_util import make_vec_env

    from sb3_dipper import DIPPER

    th.set_num_threads(1)
    env = make_vec_env("PointMazeFourRooms-v0", n_envs=1, seed=0, env_kwargs={"max_episode_steps": 50})
    model = DIPPER(
        "MultiInputPolicy",
        env,
        preference_source=f"people:{directory}",
        n_preference_pairs=4,
        option_steps=10,
        learning_starts=400,
        buffer_size=2_000,
        batch_size=16,
        pairs_per_batch=4,
        trajectory_buffer_size=20,
        policy_kwargs=dict(net_arch=[16]),
        low_policy_kwargs=dict(net_arch=[16]),
        seed=0,
    )
    model.learn(500)
    env.close()


def labelling_page_png(browser: Any) -> bytes:
    from sb3_dipper.labelling.app import serve_in_background

    logging.getLogger("werkzeug").setLevel(logging.WARNING)  # not a line per request
    with tempfile.TemporaryDirectory() as folder:
        directory = Path(folder) / "labels"
        queue_of_a_tiny_run(directory)
        server = serve_in_background(directory, "127.0.0.1", 0)
        try:
            browser.get(f"http://127.0.0.1:{server.server_port}/")
            # The page sets the pair's id and its pictures' addresses together; whole_page_png waits for the pictures.
            shown = 'return document.getElementById("pair-id").textContent'
            wait_for(lambda: browser.execute_script(shown) not in ("", "-"), "a pair on the labelling page")
            return whole_page_png(browser)
        finally:
            server.shutdown()


def readme_png(browser: Any) -> bytes:
    with tempfile.TemporaryDirectory() as folder:
        page = Path(folder) / "README.html"
        page.write_text(readme_html(), encoding="utf-8")
        browser.get(page.as_uri())
        return whole_page_png(browser)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.parse_args()
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    browser = start_chromium()
    try:
        for name, shoot in ((README_PNG, readme_png), (PAGE_PNG, labelling_page_png)):
            (SCREENSHOTS / name).write_bytes(shoot(browser))
            print(f"wrote {(SCREENSHOTS / name).relative_to(REPO)}")
    finally:
        browser.quit()
    FINGERPRINTS.write_text(json.dumps(fingerprints(), indent=2) + "\n", encoding="utf-8")
    print(f"wrote {FINGERPRINTS.relative_to(REPO)}")


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    main()
