"""A map's length units from its file's CRS (formats/las.py ``crs_units``, map/source.py
``header_units``): files written by laspy with pyproj CRSs, as a WKT VLR (LAS 1.4) or
GeoTIFF keys (LAS 1.2), and a file whose keys say only the unit code."""
from __future__ import annotations

import logging

import pytest

from pointflow.formats.las import crs_units
from pointflow.map.source import header_units

from .mapfiles import write_las


def _units(path: str):
    import laspy

    with laspy.open(path) as f:
        return crs_units(f.header)


@pytest.mark.parametrize("crs, fmt, want", [
    ("EPSG:32610", 7, {"xy": "m", "z": "m"}),             # UTM 10N, WKT
    ("EPSG:2992", 7, {"xy": "ft", "z": "ft"}),            # Oregon Lambert (ft), WKT
    ("EPSG:2992", 3, {"xy": "ft", "z": "ft"}),            # the same as GeoTIFF keys (LAS 1.2)
    ("EPSG:2264", 3, {"xy": "US ft", "z": "US ft"}),      # NC State Plane (US survey ft), keys
    ("EPSG:32610+5703", 7, {"xy": "m", "z": "m"}),        # UTM + NAVD88 height, compound
    ("EPSG:2992+6360", 7, {"xy": "ft", "z": "US ft"}),    # feet, heights in US survey feet
    ("EPSG:4326", 7, None),                               # degrees: no length unit
    (None, 7, None),                                      # no CRS at all
])
def test_units_come_from_the_files_crs(tmp_path, crs, fmt, want):
    p = write_las(str(tmp_path / "t.las"), 100, point_format=fmt, crs=crs)
    assert _units(p) == want


def test_user_defined_keys_with_a_unit_code(tmp_path):
    """GeoTIFF keys with a user-defined projection (32767) that pyproj cannot build a CRS from:
    the ProjLinearUnitsGeoKey (3076) and VerticalUnitsGeoKey (4099) still say the units."""
    import laspy
    from laspy.vlrs.geotiff import GeoKeyEntryStruct
    from laspy.vlrs.known import GeoKeyDirectoryVlr

    p = write_las(str(tmp_path / "t.las"), 100)
    las = laspy.read(p)
    vlr = GeoKeyDirectoryVlr()
    keys = [(1024, 1), (3072, 32767), (3076, 9003), (4099, 9001)]
    vlr.geo_keys_header.number_of_keys = len(keys)
    vlr.geo_keys = [GeoKeyEntryStruct(k, 0, 1, v) for k, v in keys]
    las.header.vlrs.append(vlr)
    las.write(p)
    assert _units(p) == {"xy": "US ft", "z": "m"}


def test_a_map_whose_files_disagree_is_said_and_unlabelled(tmp_path, caplog):
    a = write_las(str(tmp_path / "a.las"), 100, crs="EPSG:2992")
    b = write_las(str(tmp_path / "b.las"), 100, seed=1, crs="EPSG:32610")
    c = write_las(str(tmp_path / "c.las"), 100, seed=2)
    log = logging.getLogger("test_units")
    assert header_units([a], log) == {"xy": "ft", "z": "ft"}
    with caplog.at_level(logging.WARNING):
        assert header_units([a, b], log) == {"xy": "", "z": ""}
    assert "a.las ft, b.las m" in caplog.text
    assert header_units([a, c], log) is None, "a file without a CRS: the views take metres"
    assert header_units([str(tmp_path / "d.ply")], log) is None, "PLY says no units"


def test_map_units_in_the_config_win(tmp_path):
    """map.units labels a map whose file says nothing (or says wrong): a view's frames carry it."""
    from pointflow import Pipeline
    from pointflow.config import ConfigError, load_config
    from view.test_views import ViewClient  # tests/ is on the path (rootdir)

    las = write_las(str(tmp_path / "t.las"), 2000)
    with pytest.raises(ConfigError, match="map.units: expected a short unit label"):
        load_config({"map": {"path": las, "units": "x" * 40}})
    cfg = {"map": {"path": las, "units": "US ft", "cache_dir": str(tmp_path / "c")},
           "render": {"backend": "cpu", "size": [64, 48], "output": {"every_n_frames": 100000}}}
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        pipe.wait(120, until=lambda: pipe.stats()["stages"]["render"].get("map_points", 0) >= 2000)
        cl = ViewClient(pipe._sup.endpoints.views)
        try:
            cl.send(view="u", cmd="open", width=64, height=48, req=1)
            cl.reply("u", 1)
            cl.send(view="u", cmd="credit", n=2)
            head = cl.frame("u", 0, timeout_s=120)[0]
            assert head["units"] == {"xy": "US ft", "z": "US ft"}, head.get("units")
        finally:
            cl.close()
