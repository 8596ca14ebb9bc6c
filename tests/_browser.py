"""Headless Chromium for viewer tests (Debian packages ``chromium`` and ``chromium-driver``; ``.ci/run``
installs them). Software WebGL2 through ANGLE + SwiftShader, a fresh profile per browser, no network
services. Absent browser: the test skips on a user's machine and fails under ``CI=true``.

Screenshots kept by the tests go to pytest's ``tmp_path`` and are copied to ``tests/artifacts/``
(ignored by git); the path is printed (``pytest -s`` shows it).
"""

from __future__ import annotations

import shutil
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from tests._ci import missing

ARTIFACTS = Path(__file__).resolve().parent / "artifacts"
CHROMIUM_FLAGS = ["--headless=new", "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                  "--no-sandbox", "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--no-first-run", "--disable-dev-shm-usage", "--window-size=640,480", "--hide-scrollbars"]


def require_chromium() -> tuple[str, str]:
    """(chromium binary, chromedriver binary); skip (fail under CI=true) when missing."""
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    try:
        import selenium  # noqa: F401
    except ImportError:
        driver = None
    if not (browser and driver):
        msg = ("headless Chromium not available (need Debian packages chromium + chromium-driver and the "
               "selenium Python package; `apt-get install chromium chromium-driver`)")
        missing(msg)
    return browser, driver


@contextmanager
def headless_chromium():
    """A selenium Chrome WebDriver on headless Chromium with a fresh ``--user-data-dir`` (removed after)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    browser, driver_bin = require_chromium()
    profile = tempfile.mkdtemp(prefix="gausslite-chromium-")
    opts = Options()
    opts.binary_location = browser
    for flag in CHROMIUM_FLAGS + [f"--user-data-dir={profile}"]:
        opts.add_argument(flag)
    driver = webdriver.Chrome(options=opts, service=Service(driver_bin))
    driver.set_page_load_timeout(60)
    try:
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


def screenshot(driver) -> np.ndarray:
    """The viewport as (H, W, 3) uint8 RGB."""
    import cv2

    png = driver.get_screenshot_as_png()
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


HIDE_OVERLAYS_JS = """
const s = document.createElement('style');
s.textContent = '* { visibility: hidden !important; } canvas { visibility: visible !important; }';
document.head.appendChild(s);
"""


def hide_overlays(driver) -> None:
    """Hide every page element except the WebGL canvas (viser's control panel, notifications, logo), so
    a screenshot shows only the 3D scene and pixel-change measures are not moved by GUI toasts that come
    and go. Visibility, not display: layout and the canvas size stay as they are."""
    driver.execute_script(HIDE_OVERLAYS_JS)


def changed_fraction(a: np.ndarray, b: np.ndarray, threshold: int = 24) -> float:
    """Fraction of pixels whose largest channel difference exceeds ``threshold`` (0..255)."""
    assert a.shape == b.shape, (a.shape, b.shape)
    diff = np.abs(a.astype(np.int16) - b.astype(np.int16)).max(axis=2)
    return float((diff > threshold).mean())


def wait_until_still(driver, timeout_s: float = 60.0, interval_s: float = 0.25) -> np.ndarray:
    """Screenshots ``interval_s`` apart until two in a row are alike (:func:`changed_fraction` 0): the page shows what
    it has drawn. Returns the last one (the last taken when ``timeout_s`` passes first)."""
    from selenium.common.exceptions import TimeoutException

    deadline = time.monotonic() + timeout_s
    prev = None
    while True:
        try:
            img = screenshot(driver)
        except TimeoutException:  # swiftshader busy rendering on a loaded CPU: ask again until the deadline
            img = prev
        if img is not None and prev is not None and img is not prev and changed_fraction(img, prev) == 0.0:
            return img
        if time.monotonic() >= deadline and img is not None:
            return img
        prev = img
        time.sleep(interval_s)


def wait_for_change(driver, reference: np.ndarray, min_fraction: float, timeout_s: float = 240.0) -> tuple:
    """Take screenshots until the changed fraction vs ``reference`` exceeds ``min_fraction`` and is stable
    (two shots within 0.5 percentage points), or ``timeout_s`` passes. Returns (image, fraction)."""
    deadline = time.monotonic() + timeout_s
    prev = -1.0
    img, frac = reference, 0.0
    from selenium.common.exceptions import TimeoutException

    while time.monotonic() < deadline:
        time.sleep(1.0)
        try:
            img = screenshot(driver)
        except TimeoutException:  # swiftshader busy rendering on a loaded CPU: ask again until the deadline
            continue
        frac = changed_fraction(img, reference)
        if frac >= min_fraction and abs(frac - prev) < 0.005:
            break
        prev = frac
    return img, frac


def keep_artifact(img: np.ndarray, tmp_path: Path, name: str) -> Path:
    """Write ``img`` to ``tmp_path/name`` and copy it to ``tests/artifacts/name``; prints both paths."""
    import cv2

    out = tmp_path / name
    cv2.imwrite(str(out), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    ARTIFACTS.mkdir(exist_ok=True)
    kept = ARTIFACTS / name
    shutil.copyfile(out, kept)
    print(f"viewer screenshot: {kept} (also {out})")
    return kept
