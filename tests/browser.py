"""Open a page in headless Chromium (Debian's chromium and chromium-driver, ``make browser``)
through Selenium: the screenshot, the console's errors and the time until the page had drawn.

Used by ``tests/test_htmlreport.py`` and ``benchmarks/bench_report.py``. :func:`missing` says
why no browser can be driven here (the tests skip with it).
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path

CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"


@dataclass
class Visit:
    """What a page did in the browser."""

    screenshot: bytes  # PNG of the window
    errors: list[str]  # console messages at level SEVERE (JavaScript errors, console.error)
    seconds: float  # from the request until the page said it had drawn (or until it loaded)
    rendered: bool  # the page set data-sdp-rendered (the plotly view has drawn)


def missing() -> str | None:
    """Why a browser can't be driven here, or None."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (pip install 'sdp[test]')"
    for exe in (CHROMIUM, CHROMEDRIVER):
        if not Path(exe).exists() and not shutil.which(Path(exe).name):
            return f"{exe} is missing: `make browser` installs Debian's chromium and chromium-driver"
    return None


def visit(path, *, width: int = 1280, height: int = 1800, timeout: float = 300.0) -> Visit:
    """Open ``path`` (a local file) in headless Chromium, wait until it has drawn, and return what it did
    (``timeout``: a guard against a page that never draws, not a measure of its speed)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM if Path(CHROMIUM).exists() else shutil.which("chromium")
    # WebGL for plotly's 3-D view without a GPU: SwiftShader, which Chromium only uses when asked
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={width},{height}",
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-extensions"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    service = Service(CHROMEDRIVER if Path(CHROMEDRIVER).exists() else shutil.which("chromedriver"))
    driver = webdriver.Chrome(service=service, options=options)
    try:
        driver.set_page_load_timeout(timeout)
        t0 = time.perf_counter()
        driver.get(Path(path).resolve().as_uri())
        rendered = False
        while time.perf_counter() - t0 < timeout:
            if driver.execute_script("return document.documentElement.dataset.sdpRendered === 'yes'"):
                rendered = True
                break
            if not driver.execute_script("return document.querySelector('.plotly-graph-div') !== null"):
                break  # a page without a 3-D view: loaded is drawn
            time.sleep(0.02)
        seconds = time.perf_counter() - t0
        shot = driver.get_screenshot_as_png()
        errors = [e["message"] for e in driver.get_log("browser") if e.get("level") == "SEVERE"]
    finally:
        driver.quit()
    return Visit(shot, errors, seconds, rendered)


def blankness(png: bytes) -> float:
    """The standard deviation of the screenshot's grey levels (0: one flat colour)."""
    import io

    import matplotlib.image as mpimg
    import numpy as np

    img = mpimg.imread(io.BytesIO(png), format="png")
    grey = np.asarray(img[..., :3], np.float64).mean(axis=2)
    return float(grey.std())
