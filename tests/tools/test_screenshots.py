"""The screenshots in docs/_static/screenshots/ (``make screenshots``) are 1280-px-wide PNGs of the current sources.

No browser here: the files are read as bytes, and ``screenshots.json`` records the fingerprint of what each one shows
(:mod:`zoo_scripts.screenshots`), which must match the sources now.
"""

import json
import struct

import pytest

from zoo_scripts.screenshots import FINGERPRINTS, SCREENSHOTS, WIDTH, fingerprints, readme_outline

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_size(data: bytes) -> tuple[int, int]:
    """Width and height from a PNG's header (its first chunk, IHDR)."""
    assert data[:8] == PNG_SIGNATURE and data[12:16] == b"IHDR", "not a PNG file"
    width, height = struct.unpack(">II", data[16:24])
    return width, height


@pytest.mark.parametrize("name", sorted(fingerprints()))
def test_each_screenshot_is_a_whole_page_1280_px_wide(name):
    width, height = png_size((SCREENSHOTS / name).read_bytes())
    assert width == WIDTH and height >= 600


def test_the_screenshots_show_the_current_sources():
    recorded = json.loads(FINGERPRINTS.read_text(encoding="utf-8"))
    current = fingerprints()
    stale = sorted(name for name in current if recorded.get(name) != current[name])
    assert not stale, (
        f"{stale} in {SCREENSHOTS} show older sources than {[current[name]['sources'] for name in stale]}: run "
        "`make screenshots` (python zoo_scripts/screenshots.py) and commit what it writes"
    )


def test_the_readme_fingerprint_follows_its_layout_not_its_wording():
    readme = (
        "# Title\n\nSome words.\n\n| task | success |\n|---|---|\n| maze | 0.91 |\n\n![curves](a.png)\n\n"
        "```bash\nmake demo\n```\n"
    )
    outline = readme_outline(readme)
    reworded = readme.replace("Some words", "Other words").replace("0.91", "0.95")
    reworded = reworded.replace("make demo", "# a comment in a code block\nmake test")
    assert readme_outline(reworded) == outline
    for changed in (
        readme.replace("# Title", "# Another title"),
        readme.replace("| task | success |", "| task | success | seeds |"),
        readme.replace("a.png", "b.png"),
        readme.replace("```bash", "```python"),
        readme + "\n## A new section\n",
    ):
        assert readme_outline(changed) != outline
