"""The `mcdenoise eval` page in a real browser: headless Chromium renders index.html.

Slow (starts a browser twice). Needs a ``chromium`` binary (Debian: ``apt-get install -y chromium``);
skipped with that reason when none is found.
"""

from __future__ import annotations

import re
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from mcdenoise.eval import evaluate
from train_tiny_data import make_tiny_dataset

pytestmark = pytest.mark.slow

_BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--virtual-time-budget=10000")

# Appended to a copy of the page (the report itself has no scripts): after every image has
# loaded or failed, write "src complete naturalWidth naturalHeight" per <img> into the DOM.
_CHECK = """<script>
window.addEventListener('load', function () {
  var out = [];
  for (var i = 0; i < document.images.length; i++) {
    var im = document.images[i];
    out.push(im.getAttribute('src') + ' ' + im.complete + ' ' + im.naturalWidth + ' ' + im.naturalHeight);
  }
  var pre = document.createElement('pre');
  pre.id = 'imgcheck';
  pre.textContent = out.join('\\n');
  document.body.appendChild(pre);
});
</script>"""


def _browser() -> str:
    for name in _BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    pytest.skip(f"no Chromium binary found ({', '.join(_BROWSERS)}); install one, e.g. apt-get install -y chromium")


def _png_size(path: Path) -> tuple[int, int]:
    w, h = struct.unpack(">II", path.read_bytes()[16:24])
    return w, h


@pytest.fixture(scope="module")
def page(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from safetensors.torch import save_file

    from mcdenoise.models.registry import build_model

    _browser()  # skip before building anything
    root = tmp_path_factory.mktemp("browser")
    data = make_tiny_dataset(root / "data", train=0, val=2, spp=8, size=24)
    model = build_model("wskp", "small")
    weights = root / "wskp_rand.safetensors"
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(weights),
              metadata={"model": "wskp", "preset": "small"})
    evaluate(models=[str(weights)], data=[data], split="val", spp=[2, 8], out=root / "report", threads=1, progress=False)
    return root / "report" / "index.html"


def test_screenshot_is_not_blank(page: Path, tmp_path: Path) -> None:
    """Catches a page that renders empty (broken markup, everything hidden) in a real browser."""
    from matplotlib.image import imread

    shot = tmp_path / "shot.png"
    subprocess.run([_browser(), *_FLAGS, "--window-size=1200,1600", f"--screenshot={shot}", page.as_uri()],
                   check=True, capture_output=True, timeout=120)
    img = np.asarray(imread(shot))[..., :3]
    assert img.shape[:2] == (1600, 1200)
    non_white = (img < 0.9).any(axis=-1).mean()
    assert non_white > 0.05, f"only {non_white:.1%} of the screenshot is not white"
    assert img.std() > 0.1


def test_every_image_decodes(page: Path) -> None:
    """Catches <img> tags whose file is missing, misnamed or not a decodable PNG: the browser
    reports naturalWidth 0 for those. A deliberately missing image proves the check can fail."""
    html = page.read_text()
    n_imgs = len(re.findall(r"<img\s", html))
    check = page.with_name("check.html")
    check.write_text(html.replace("</body>", "<img src='missing.png' alt='probe'>" + _CHECK + "</body>"))
    dom = subprocess.run([_browser(), *_FLAGS, "--dump-dom", check.as_uri()], check=True, capture_output=True,
                         text=True, timeout=120).stdout
    m = re.search(r"<pre id=\"imgcheck\">(.*?)</pre>", dom, re.S)
    assert m, "the check script did not run"
    lines = [line.split() for line in m.group(1).strip().splitlines()]
    assert len(lines) == n_imgs + 1
    *real, probe = lines
    assert probe[0] == "missing.png" and probe[2] == "0"
    for src, complete, w, h in real:
        assert complete == "true" and int(w) > 0, f"{src} did not load"
        assert (int(w), int(h)) == _png_size(page.parent / src), src
