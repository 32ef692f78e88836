"""Fixtures for the phone web page tests: a headless Chromium driven by Playwright's sync API.

Chromium is Debian's package (``/usr/bin/chromium``), never a browser build downloaded by
``playwright install``; without it the tests skip and say how to install it.
"""

from __future__ import annotations

import logging
import shutil
from typing import TYPE_CHECKING

import pytest
from wait_helpers import DEADLINE_S

if TYPE_CHECKING:
    from collections.abc import Iterator

    from playwright.sync_api import Browser, Page

log = logging.getLogger(__name__)

#: A phone-sized touch viewport (CSS px).
PHONE_VIEWPORT = {"width": 390, "height": 844}


@pytest.fixture(scope="session")
def browser() -> Iterator[Browser]:
    """One headless Chromium for the session (Debian's ``chromium``; skips when it is missing)."""
    sync_api = pytest.importorskip("playwright.sync_api",
                                   reason="playwright is not installed: pip install -e '.[test]'")
    exe = shutil.which("chromium")
    if exe is None:
        pytest.skip("chromium not found on PATH: install Debian's package (sudo apt-get install chromium); "
                    "the phone page tests do not use browsers downloaded by `playwright install`")
    pw = sync_api.sync_playwright().start()
    try:
        b = pw.chromium.launch(executable_path=exe, headless=True, args=["--ignore-certificate-errors"])
        log.info("chromium %s at %s", b.version, exe)
        try:
            yield b
        finally:
            b.close()
    finally:
        pw.stop()


@pytest.fixture
def page(browser: Browser) -> Iterator[Page]:
    """A fresh phone-like page (own context: empty storage, touch enabled, mobile viewport)."""
    context = browser.new_context(viewport=PHONE_VIEWPORT, is_mobile=True, has_touch=True, ignore_https_errors=True)
    context.set_default_timeout(DEADLINE_S * 1000)  # every wait: a deadline only a broken page reaches
    try:
        yield context.new_page()
    finally:
        context.close()


@pytest.fixture
def console_errors(page: Page) -> list[str]:
    """Console errors and uncaught exceptions of ``page``, collected from before the first navigation."""
    errors: list[str] = []
    page.on("console", lambda m: errors.append(f"console.{m.type}: {m.text}") if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(f"uncaught: {e}"))
    return errors
