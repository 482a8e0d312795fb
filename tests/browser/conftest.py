"""Browser-test fixtures: Debian's headless Chromium (driven by playwright) and a real
texspace server on a free loopback port with a temporary data dir.

Set TEXSPACE_BROWSER_BASE_URL to drive an already running server instead.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.browser.helpers import CHROMIUM, CHROMIUM_FLAGS, serve

ARTIFACTS = Path(__file__).resolve().parents[1] / "artifacts" / "browser"
REPO = Path(__file__).resolve().parents[2]


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    skip = pytest.mark.skip(reason=f"{CHROMIUM} is absent: run tests/browser/install.sh (Debian chromium)")
    for item in items:
        if "tests/browser/" in str(item.fspath).replace(os.sep, "/"):
            item.add_marker(pytest.mark.browser)
            item.add_marker(pytest.mark.e2e)
            if not CHROMIUM.exists():
                item.add_marker(skip)


@pytest.fixture(scope="session")
def artifacts() -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    return ARTIFACTS


@pytest.fixture(scope="session")
def base_url(tmp_path_factory: pytest.TempPathFactory, artifacts: Path) -> Iterator[str]:
    """URL of a running texspace service (API + page at /)."""
    external = os.environ.get("TEXSPACE_BROWSER_BASE_URL")
    if external:
        yield external.rstrip("/") + "/"
        return
    data_dir = tmp_path_factory.mktemp("texspace-data")
    env = {**os.environ, "TEXSPACE_DATA_DIR": str(data_dir), "TEXSPACE_AUTO_FIT": "false"}
    with serve(data_dir, artifacts / "server.log", env) as url:
        yield url


@pytest.fixture(scope="session")
def keyed_server(tmp_path_factory: pytest.TempPathFactory, artifacts: Path) -> Iterator[tuple[str, str]]:
    """(URL, API key) of a texspace service of its own with API keys on (as in compose.yaml);
    the key is made the way an admin does, with ``texspace keys create``."""
    data_dir = tmp_path_factory.mktemp("texspace-keyed-data")
    env = {**os.environ, "TEXSPACE_DATA_DIR": str(data_dir), "TEXSPACE_API_KEYS_ENABLED": "true",
           "TEXSPACE_API_KEY_PEPPER": "browser-test-pepper", "TEXSPACE_AUTO_FIT": "false"}
    made = subprocess.run([sys.executable, "-m", "service.cli", "keys", "create", "browser-test"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=120, check=True)
    key = re.search(r"^key: +(\S+)$", made.stdout, re.M)
    assert key, f"no key in the output of texspace keys create:\n{made.stdout}\n{made.stderr}"
    with serve(data_dir, artifacts / "server-keyed.log", env) as url:
        yield url, key[1]


@pytest.fixture(scope="session")
def refining_server(tmp_path_factory: pytest.TempPathFactory, artifacts: Path) -> Iterator[str]:
    """URL of a texspace service of its own that refines every upload (TEXSPACE_AUTO_FIT, the
    default where torch is installed) with a short real fit, and a short detail stage where no
    other fit waits (the 512-px test photos have one)."""
    pytest.importorskip("torch", reason="refinement needs the train extra")
    data_dir = tmp_path_factory.mktemp("texspace-refining-data")
    env = {**os.environ, "TEXSPACE_DATA_DIR": str(data_dir), "TEXSPACE_AUTO_FIT": "true",
           "TEXSPACE_FIT_SECONDS": "3", "TEXSPACE_REFINE_DETAIL_SECONDS": "2"}
    with serve(data_dir, artifacts / "server-refining.log", env) as url:
        yield url


@pytest.fixture(scope="session")
def playwright():
    """The session's one playwright driver (its sync API allows one per thread)."""
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is in the test extra")
    with sync_api.sync_playwright() as driver:
        yield driver


@pytest.fixture(scope="session")
def browser(tmp_path_factory: pytest.TempPathFactory, playwright):
    profile = tmp_path_factory.mktemp("chromium-profile")
    # A persistent context is how playwright takes a fresh --user-data-dir.
    context = playwright.chromium.launch_persistent_context(
        str(profile), executable_path=str(CHROMIUM), headless=True,
        args=CHROMIUM_FLAGS, viewport={"width": 1400, "height": 1300},
    )
    try:
        yield context
    finally:
        context.close()


@pytest.fixture
def page(browser):
    page = browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    # Uncaught exceptions and console errors (failed requests among them): tests assert none.
    page.on("console", lambda message: errors.append(message.text) if message.type == "error" else None)
    page.js_errors = errors
    yield page
    page.close()
