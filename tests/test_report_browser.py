"""The diagnosis report in a real browser (headless Chromium): every image decodes, the
verdict box is visible above the fold, and a screenshot shows it.

The report comes from the real command (`jaxwear diagnose`) on a tiny synthetic study (two
experiments, 32 nodes × 32 steps): a rendering test, not a test of the diagnosis. The probe
script is appended to a copy of the report (the report itself has no script). Skipped, with
the reason, when no Chromium is installed (`.ci/run` installs Debian's `chromium`).
"""

import json
import os
import re
import shutil
import subprocess

import numpy as np
import pytest

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
BROWSER = next((shutil.which(b) for b in BROWSERS if shutil.which(b)), None)
pytestmark = pytest.mark.skipif(
    BROWSER is None, reason="no headless Chromium on PATH (install Debian's `chromium`: "
                            "apt-get install -y chromium; .ci/run does)")

CONDITIONS = """\
[model]
preset = "rig"
[model.parameters]
K_d_per_Pa = 1.0e-13
spring_N_per_m = 1009.4
[numerics]
nodes = 32
steps_per_rev = 32
revolutions_per_update = 500
[[experiment]]
name = "n276"
speed_rpm = 276
revolutions = 4000
clearance_mm = 0.05
[[experiment]]
name = "n148"
speed_rpm = 148
revolutions = 4000
clearance_mm = 0.10
"""

PROBE = """
<pre id="probe"></pre>
<script>
window.addEventListener("load", () => {
  const imgs = [...document.images].map(i => ({
    ok: i.complete && i.naturalWidth > 0 && i.naturalHeight > 0,
    w: i.naturalWidth, h: i.naturalHeight, alt: i.alt}));
  const v = document.querySelector(".verdict");
  let verdict = null;
  if (v) {
    const r = v.getBoundingClientRect(), s = getComputedStyle(v);
    verdict = {w: r.width, h: r.height, top: r.top, display: s.display,
               visibility: s.visibility, opacity: s.opacity, border: s.borderLeftColor,
               text: v.innerText, viewport: window.innerHeight};
  }
  document.getElementById("probe").textContent = JSON.stringify({imgs, verdict});
});
</script>
"""

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
         "--hide-scrollbars", "--no-first-run", "--window-size=1200,1600"]


def _chromium(args, tmp_path, timeout=120):
    env = dict(os.environ, HOME=str(tmp_path))  # a fresh profile, nothing from the user
    return subprocess.run([BROWSER, *FLAGS, f"--user-data-dir={tmp_path / 'profile'}", *args],
                          capture_output=True, text=True, timeout=timeout, env=env)


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    from jaxwear import synthesize
    from jaxwear.cli import main

    d = tmp_path_factory.mktemp("report")
    (d / "conditions.toml").write_text(CONDITIONS)
    res = synthesize(["running_in"], str(d / "conditions.toml"), noise_um=0.3, seed=5,
                     out=d / "study")
    assert main(["diagnose", str(res.study_path), "--out", str(d / "out")]) == 0
    return d / "out" / "report.html"


def test_report_renders_in_chromium(report, tmp_path):
    html = report.read_text(encoding="utf-8")
    n_img = html.count("<img")
    assert n_img >= 3
    probe = tmp_path / "probe.html"
    probe.write_text(html.replace("</body>", PROBE + "</body>"), encoding="utf-8")
    proc = _chromium(["--dump-dom", probe.as_uri()], tmp_path)
    m = re.search(r'<pre id="probe">(.*?)</pre>', proc.stdout, flags=re.S)
    assert m and m.group(1).strip(), f"no probe result; stderr: {proc.stderr[-2000:]}"
    got = json.loads(m.group(1).replace("&quot;", '"').replace("&amp;", "&")
                     .replace("&lt;", "<").replace("&gt;", ">"))
    imgs = got["imgs"]
    assert len(imgs) == n_img
    bad = [i["alt"] for i in imgs if not i["ok"]]
    assert not bad, f"images that do not decode: {bad}"
    assert all(i["w"] >= 100 and i["h"] >= 100 for i in imgs)
    v = got["verdict"]
    assert v is not None, "no .verdict box"
    assert v["display"] != "none" and v["visibility"] == "visible" and float(v["opacity"]) > 0
    assert v["w"] > 300 and v["h"] > 30
    assert 0 <= v["top"] < v["viewport"], "the verdict is not above the fold"
    assert v["text"].strip()
    # The screenshot, kept in the test's temporary folder: the verdict's coloured border
    # must be on it (a vertical strip of the border colour at least the box's height).
    shot = tmp_path / "report.png"
    proc = _chromium([f"--screenshot={shot}", report.as_uri()], tmp_path)
    assert shot.exists() and shot.stat().st_size > 10_000, proc.stderr[-2000:]
    import matplotlib.image as mpimg

    px = (mpimg.imread(str(shot))[..., :3] * 255).round().astype(int)
    rgb = np.array([int(x) for x in re.findall(r"\d+", v["border"])[:3]])
    match = np.all(np.abs(px - rgb) <= 8, axis=-1)
    column = match.sum(axis=0).max()
    assert column >= 0.8 * v["h"], (column, v["h"], v["border"])
    assert px.std() > 10  # not a blank page
