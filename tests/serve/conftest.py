"""One pipeline with a view server for the hostile-client modules (test_hostile.py,
test_attacks.py): a pipeline costs seconds to start on a loaded machine, and the two need
the same thing, a synthetic lidar drawn by the cpu tier at 96x72 with tight limits."""
from __future__ import annotations

import pytest

from pointflow import Pipeline

from .helpers import base_url, config, synthetic_source

#: Tight so the tests are short: a flood, an oversized message, a stuck send, a slow head.
LIMITS = {"max_message_bytes": 4096, "max_messages_per_s": 50.0, "send_timeout_s": 3.0, "queue_frames": 2,
          "header_timeout_s": 2.0}


@pytest.fixture(scope="package")
def hostile_pipe(tmp_path_factory):
    cfg = config(synthetic_source(), serve={"limits": LIMITS, "width": 96, "height": 72,
                                            "allowed_hosts": ["view.example.org"]}, size=(96, 72))
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path_factory.mktemp("hostile"))) as p:
        base_url(p)
        p.wait(60, until=lambda: p.stats()["stages"]["render"].get("frames", 0) > 2)
        yield p


@pytest.fixture(scope="module")
def browser():
    """One headless Chromium per test file that asks for it (tests/serve/browser.py)."""
    from .browser import launch, need_browser

    sync_api = need_browser()
    with sync_api.sync_playwright() as pw:
        b = launch(pw)
        yield b
        b.close()
