import pytest

from gpu_util import require_adapter


@pytest.fixture
def make_renderer():
    """Factory for WgpuRenderers on the test adapter; closes them after the test."""
    adapter = require_adapter()
    from pointflow.render.wgpu_tier import WgpuRenderer
    made = []

    def make(cfg, capacity, channels=(), **kw):
        r = WgpuRenderer(cfg, capacity, list(channels), adapter=adapter, **kw)
        made.append(r)
        return r

    yield make
    for r in made:
        r.close()
