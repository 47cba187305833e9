"""``comgs view`` in a real browser: the command runs in a subprocess on a tiny two-object
composition, headless Chromium (Debian's ``/usr/bin/chromium``, driven by playwright; no
``playwright install``) opens it, waits for the first composite frame, moves object ``a``
through the viewer's GUI (its position field and "apply move of a", the path a gizmo's
release takes), saves the placement, and checks that ``transform.json`` and the frame shown
changed accordingly. Skipped when Chromium or playwright is missing (``setup.sh`` installs
both)."""
import base64
import io
import json
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

CHROMIUM = Path("/usr/bin/chromium")
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]
DY = 0.5          # the move typed in the GUI: +0.5 along world y
DX = 0.3          # then the gizmo dragged with the mouse: +0.3 along world x


def _requirements():
    if not CHROMIUM.is_file():
        pytest.skip(f"{CHROMIUM} not found: `apt-get install -y chromium` (setup.sh does)")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        pytest.skip("playwright not installed: pip install playwright (the [dev] extra)")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _shown_image(page) -> np.ndarray:
    """The composite panel's image, decoded (RGB uint8)."""
    from PIL import Image
    b64 = page.evaluate("""async () => {
        const img = [...document.querySelectorAll('img')].find(i => i.src.startsWith('blob:'));
        const blob = await (await fetch(img.src)).blob();
        const buf = new Uint8Array(await blob.arrayBuffer());
        let s = ''; for (const b of buf) s += String.fromCharCode(b);
        return btoa(s);
    }""")
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(b64))).convert("RGB"))


def _drag_gizmo_x(page, home: dict, size: float, centre, dx: float):
    """Drag the gizmo at ``centre`` by ``dx`` along world x with the mouse: from its x
    arrow (0.7 of its length, 0.6 × the object's ``size``, from the centre) to ``dx``
    further, seen from camera ``home`` (where the server put this viewer, up +Z)."""
    from comgs_dr.view.session import camera_pose_cv, wxyz_rotation
    p, q, fov = camera_pose_cv(home)
    r = wxyz_rotation(q)
    w, h = page.viewport_size["width"], page.viewport_size["height"]
    f = 0.5 * h / np.tan(0.5 * fov)

    def px(x):
        c = r.T @ (np.asarray(x, np.float64) - p)
        return w / 2 + f * c[0] / c[2], h / 2 + f * c[1] / c[2]
    start = np.asarray(centre) + [0.7 * 0.6 * size, 0, 0]
    (x0, y0), (x1, y1) = px(start), px(start + [dx, 0, 0])
    page.mouse.move(x0, y0)
    page.mouse.down()
    for t in np.linspace(0, 1, 15)[1:]:
        page.mouse.move(x0 + t * (x1 - x0), y0 + t * (y1 - y0))
        page.wait_for_timeout(30)
    page.mouse.up()
    return (x0, y0), (x1, y1)


def _wait_status(page, pattern: str, timeout_s: float = 240.0) -> str:
    """The first status paragraph matching the regular expression ``pattern``, once there
    is one."""
    page.wait_for_function("p => [...document.querySelectorAll('p')].some(e => "
                           "new RegExp(p).test(e.textContent))", arg=pattern,
                           timeout=timeout_s * 1000)
    return page.evaluate("p => [...document.querySelectorAll('p')].map(e => e.textContent)"
                         ".find(s => new RegExp(p).test(s))", pattern)


def test_view_in_headless_chromium(tmp_path):
    _requirements()
    from playwright.sync_api import sync_playwright
    from test_view import A0, B0, make_two_ball_comp
    t_start = time.perf_counter()
    from comgs_dr.view.session import ViewConfig, ViewSession
    comp = make_two_ball_comp(tmp_path)
    s = ViewSession(comp, ViewConfig())
    home = s.home_camera(48)               # where the server will put the viewer's camera
    size = float(np.linalg.norm(np.subtract(*s.bounds("a"))))
    port = _free_port()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    log = open(tmp_path / "view.log", "w")          # a file: a full pipe would block it
    proc = subprocess.Popen([sys.executable, "-m", "comgs_dr.cli", "view", str(comp), "--port",
                             str(port), "--res", "48", "--rays", "4", "--quiet",
                             "--mitsuba-variant", "llvm_ad_rgb"],
                            stdout=log, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        deadline = time.time() + 180
        while f"comgs view: http://localhost:{port}" not in (tmp_path / "view.log").read_text():
            assert proc.poll() is None, "comgs view exited: " + (tmp_path / "view.log").read_text()
            assert time.time() < deadline, "comgs view did not start"
            time.sleep(0.2)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
            page = browser.new_page(viewport={"width": 1000, "height": 700})
            page.goto(f"http://127.0.0.1:{port}/")
            # the first composite from this viewer's camera (set by the server on connect)
            _wait_status(page, r"^frame \d+ \((viewer connected|camera)")
            page.wait_for_selector("img[src^='blob:']")
            before = _shown_image(page)
            assert before.shape == (48, 48, 3) and before.std() > 1
            # move a by +DY along y: its position field, then "apply move of a"
            y = page.get_by_label("a position").locator(
                "xpath=ancestor::div[contains(@class,'mantine-Flex-root')][1]//input").nth(1)
            y.fill(f"{A0[1] + DY:.3f}")
            y.press("Enter")
            page.get_by_role("button", name="apply move of a").click()
            moved_status = _wait_status(page, r"^last move .*: a moved")
            assert "from release" in moved_status, moved_status
            page.wait_for_timeout(500)
            after = _shown_image(page)
            # then a real drag of a's gizmo with the mouse: its release re-runs the edit
            n = int(re.search(r"frame (\d+)", moved_status).group(1))
            _drag_gizmo_x(page, home, size, A0 + [0, DY, 0], DX)
            page.wait_for_function(
                "n => [...document.querySelectorAll('p')].some(e => { const m = "
                "/^last move \\(frame (\\d+)\\).*: a moved/.exec(e.textContent); "
                "return m && +m[1] > n; })", arg=n, timeout=240_000)
            dragged = _shown_image(page)
            assert np.abs(dragged.astype(int) - after.astype(int)).max() > 40
            page.get_by_role("button", name="save placement").click()
            _wait_status(page, "saved the placement")
            browser.close()
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
    # transform.json: a moved by DY along y (dataset frame = world here), b where it was
    t = json.loads((comp / "transform.json").read_text())
    W = np.asarray(json.loads((comp / "composition.json").read_text())["world_from_source"])
    a = W @ np.asarray(t["a"]["transform"]).reshape(4, 4)
    b = W @ np.asarray(t["b"]["transform"]).reshape(4, 4)
    assert np.allclose(a[:3, 3], A0 + [DX, DY, 0], atol=0.08)          # the drag: ±0.08
    assert np.allclose(a[1:3, 3], (A0 + [0, DY, 0])[1:], atol=0.02)      # along x only
    assert np.allclose(b[:3, 3], B0, atol=1e-9)
    # the frame shown changed with each move, and the last is the one the viewer wrote
    assert np.abs(after.astype(int) - before.astype(int)).max() > 40
    from PIL import Image
    preview = np.asarray(Image.open(comp / "view" / "preview.png").convert("RGB"))
    assert np.abs(preview.astype(int) - dragged.astype(int)).max() <= 2
    recs = [json.loads(x) for x in (comp / "view" / "log.jsonl").read_text().splitlines()]
    moved = [r for r in recs if r.get("why") == "moved a"]
    assert len(moved) == 2            # the typed move and the drag's release, not the drag
    for r in moved:
        assert all("_a" in n.split("occ_")[1] for n in r["traced"]) and r["reused"]
    times = ", ".join(f"{r['total_s']:.2f}" for r in moved)
    print(f"browser test: {time.perf_counter() - t_start:.1f} s; release to frame {times} s")
