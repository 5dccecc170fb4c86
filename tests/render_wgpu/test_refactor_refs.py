"""The raster-method refactor (issue 17) left every image byte-identical: the agreement scenes
rendered by each raster method equal the images recorded from the code before it
(``data/refactor_refs.npz``, made by ``make_refactor_refs.py`` at commit b2b1037; the quads
images re-recorded for issue 31 item 6, which changed them on purpose)."""
from __future__ import annotations

import numpy as np
import pytest

from gpu_util import require_adapter

from .make_refactor_refs import OUT, render_all


@pytest.fixture(scope="module")
def images():
    return render_all(require_adapter())


def test_images_equal_the_recorded_pre_refactor_images(images):
    ref = np.load(OUT)
    assert sorted(ref.files) == sorted(images), "every scene x method recorded and rendered"
    for k in ref.files:
        assert ref[k].shape == images[k].shape
        bad = (ref[k] != images[k]).any(axis=-1)
        assert not bad.any(), f"{k}: {int(bad.sum())} pixels differ from the pre-refactor image"
