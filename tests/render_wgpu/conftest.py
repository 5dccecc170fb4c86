import dataclasses

import pytest

from gpu_util import require_adapter

#: every wgpu test runs with each raster method; "compute32" forces the two-pass 32-bit keys
RASTER = ["quads", "compute", "compute32"]


@pytest.fixture(params=RASTER)
def raster(request):
    return request.param


@pytest.fixture
def make_renderer(raster):
    """Factory for WgpuRenderers on the test adapter (the parametrised raster method unless
    the test's config names one); closes them after the test."""
    adapter = require_adapter()
    from pointflow.render.wgpu_tier import WgpuRenderer
    made = []

    def make(cfg, capacity, channels=(), **kw):
        if cfg.raster == "auto":
            cfg = dataclasses.replace(cfg, raster="quads" if raster == "quads" else "compute")
        if raster == "compute32":
            kw.setdefault("key64", False)
        r = WgpuRenderer(cfg, capacity, list(channels), adapter=adapter, **kw)
        made.append(r)
        return r

    yield make
    for r in made:
        r.close()
