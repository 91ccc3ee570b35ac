"""The live view in a real headless Chromium: the page shows the scene, the state, the keyframe
frustums and a frame count that grows while a run is in progress; the server binds loopback only.

Chromium comes from Debian's packages (``chromium``, ``chromium-driver``; ``.ci/run`` installs
them). Without them the browser test skips locally and fails under CI=true.
"""

from __future__ import annotations

import ipaddress
import os
import re
import shutil
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from tests.helpers import dev_dependency
from tests.tracking.sim_session import SIZE, make_tracker
from tests.viz.no_ipv6_udp import refuse_ipv6_udp, supported

dev_dependency("viser")
from kvtracker_sdk.viz.live_viewer import LOOPBACK, Viewer  # noqa: E402

# The browser stands in for the user, but it runs inside the suite, whose every connect() is
# traced: no name lookups (its own DNS client binds 0.0.0.0 and asks the machine's resolver),
# no prefetching, no Google services; the page is on 127.0.0.1; no IPv6 probe (see the fixture).
BROWSER_FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--window-size=1200,800", "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
    "--dns-prefetch-disable", "--disable-domain-reliability", "--no-pings",
    "--disable-client-side-phishing-detection", "--disable-default-apps", "--disable-extensions",
    "--disable-features=AsyncDns,OptimizationHints,MediaRouter,DialMediaRouteProvider,Translate,"
    "NetworkTimeServiceQuerying,CertificateTransparencyComponentUpdater",
)
PAGE_TIMEOUT_S = 15.0  # generous: the page polls, it never sleeps a fixed time
GATE_TIMEOUT_S = 30.0
# The camera loop waits for the test's browser checks, which take longer on a loaded machine; the
# test always releases it (finally), so this bound only ends a hang.
WORKER_GATE_TIMEOUT_S = 300.0


def _chromium() -> tuple[str, str]:
    browser, driver = shutil.which("chromium"), shutil.which("chromedriver")
    if browser is None or driver is None:
        message = ("headless Chromium is missing: apt-get install -y chromium chromium-driver "
                   "(.ci/run installs it)")
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message + " (CI=true: this is a failure, not a skip)")
        pytest.skip(message)
    return browser, driver


@pytest.fixture()
def browser(tmp_path: Path) -> Iterator[Any]:
    binary, driver_path = _chromium()
    webdriver = dev_dependency("selenium.webdriver")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for flag in BROWSER_FLAGS:
        options.add_argument(flag)
    profile = tempfile.mkdtemp(prefix="chromium-profile-")  # a fresh profile every time
    options.add_argument(f"--user-data-dir={profile}")
    # chromedriver and the Chromium it starts cannot open IPv6 UDP sockets: their reachability
    # probe to Google's DNS fails at socket() instead of connecting (no_ipv6_udp says why)
    service = Service(driver_path, popen_kw={"preexec_fn": refuse_ipv6_udp} if supported() else {})
    driver = webdriver.Chrome(options=options, service=service)
    try:
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


def _page_number(driver: Any, label: str) -> int:
    match = re.search(rf"{label}: (\d+)", driver.find_element("tag name", "body").text)
    return int(match.group(1)) if match else -1


def test_page_shows_the_run_while_it_is_in_progress(browser: Any, tmp_path: Path) -> None:
    from selenium.webdriver.support.ui import WebDriverWait

    backend = SimulatedBackend(orbit(num_frames=80, turns=0.25), seed=1)
    first_part, paused, resume, finish = 45, threading.Event(), threading.Event(), threading.Event()
    failures: list[BaseException] = []
    with Viewer(port=0) as viewer, make_tracker(backend, keyframing={"interval_frames": 20}) as tr:
        viewer.attach(tr)

        def run() -> None:  # the app's camera loop, paused twice by the test
            try:
                for frame in backend.frames(SIZE, stop=first_part + 10, textured=True):
                    if frame.index == first_part:
                        paused.set()
                        assert resume.wait(WORKER_GATE_TIMEOUT_S)
                    viewer.log_frame(frame.image, tr.push_frame(frame.image, timestamp=frame.timestamp))
                paused.set()
                assert finish.wait(WORKER_GATE_TIMEOUT_S)  # the run is still in progress meanwhile
            except BaseException as exc:  # reported by the test thread
                failures.append(exc)
                paused.set()

        worker = threading.Thread(target=run)
        worker.start()
        try:
            assert paused.wait(GATE_TIMEOUT_S) and not failures
            paused.clear()
            browser.get(viewer.url)
            wait = WebDriverWait(browser, PAGE_TIMEOUT_S)
            wait.until(lambda d: _page_number(d, "keyframe frustums") == 3)
            wait.until(lambda d: _page_number(d, "frames") == first_part)
            body = browser.find_element("tag name", "body").text
            assert "state: TRACKING (BOOTSTRAP)" in body
            assert browser.execute_script("return document.querySelectorAll('canvas').length") >= 1
            resume.set()
            assert paused.wait(GATE_TIMEOUT_S) and not failures
            wait.until(lambda d: _page_number(d, "frames") == first_part + 10)
            screenshot = tmp_path / "live_view.png"  # kept in pytest's tmp folder as an artefact
            wait.until(lambda d: d.save_screenshot(str(screenshot)) and _drawn(screenshot))
        finally:
            resume.set()
            finish.set()
            worker.join(GATE_TIMEOUT_S)
    assert not failures, failures


def _drawn(screenshot: Path) -> bool:
    """The rendered scene holds the trajectory and current camera (red lines) and the keyframe
    frustums (light blue lines). Colours are classified loosely: the browser's colour management
    shades the frustums' (40, 140, 255) to about (65, 155, 225); the map's points are darker."""
    image = cv2.imread(str(screenshot))[..., ::-1].astype(int)
    r, g, b = np.moveaxis(image[:, : image.shape[1] * 2 // 3], -1, 0)  # left of the panel
    red = ((r > 200) & (g < 110) & (b < 110)).sum()
    blue = ((b > 190) & (g > 110) & (g < 200) & (r < 120)).sum()
    return bool(red > 50 and blue > 50)


def _loopback(ip: str) -> bool:
    """127.0.0.0/8, ::1, or an IPv4-mapped loopback (::ffff:127.0.0.1)."""
    address = ipaddress.ip_address(ip.split("%")[0])
    mapped = getattr(address, "ipv4_mapped", None)
    return address.is_loopback or (mapped is not None and mapped.is_loopback)


def test_server_binds_loopback_only() -> None:
    psutil = dev_dependency("psutil")
    process = psutil.Process()
    before = {c.laddr for c in process.net_connections(kind="inet")}
    with Viewer(port=0) as viewer:
        opened = [c for c in process.net_connections(kind="inet") if c.laddr not in before]
        listening = [c for c in opened if c.status == psutil.CONN_LISTEN]
        assert [c.laddr.port for c in listening] == [viewer.port]
        assert {c.laddr.ip for c in opened} == {LOOPBACK}
        assert viewer.url == f"http://127.0.0.1:{viewer.port}"
        remote = {c.raddr.ip for c in process.net_connections(kind="inet") if c.raddr}
        assert all(_loopback(ip) for ip in remote), remote  # no telemetry: nothing connects out
    assert not [c for c in process.net_connections(kind="inet") if c.laddr.port == viewer.port
                and c.status == psutil.CONN_LISTEN]


def test_object_mode_shows_the_object_frame_and_region() -> None:
    backend = SimulatedBackend(orbit(num_frames=120, turns=0.25), seed=2)
    with Viewer(port=0) as viewer, make_tracker(backend, mode="object") as tracker:
        viewer.attach(tracker)
        for frame in backend.frames(SIZE, stop=40, textured=False, with_mask=True):
            result = tracker.push_frame(frame.image, timestamp=frame.timestamp, mask=frame.mask)
            viewer.log_frame(frame.image, result, mask=frame.mask)
        nodes = set(viewer._server.scene._handle_from_node_name)  # viser's scene graph
        assert {"/camera", "/trajectory", "/points", "/object", "/object/region"} <= nodes
        assert {f"/keyframes/kf_{i:04d}" for i in tracker.keyframe_map.keyframe_ids} <= nodes
        assert viewer.num_keyframes == tracker.map_status.num_keyframes >= 2
        assert viewer.frames == 40


def test_missing_chromium_skips_locally_and_fails_under_ci(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(shutil, "which", lambda _name: None)
    monkeypatch.delenv("CI", raising=False)
    with pytest.raises(pytest.skip.Exception, match="apt-get install -y chromium"):
        _chromium()
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="CI=true"):
        _chromium()
