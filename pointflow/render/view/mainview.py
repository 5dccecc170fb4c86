"""The main view: the render stage's own view (the one PNGs, the window, picks and saves
show), steered down one path by every client, and kept for a restarted render stage.

``stage`` is the render stage's state (render/process.py ``_Stage``): ``view`` (a
:class:`~pointflow.render.view.controller.ViewController`), ``renderer``, ``window``,
``capacity``, ``channels``, ``frames``, ``full_upload``.
"""
from __future__ import annotations

import dataclasses
import json
import os
from typing import Optional

from ..base import Renderer
from . import protocol
from .controller import ViewController
from .protocol import ControlError, ViewState, style_render_config

__all__ = ["steer", "window_control", "keep", "restore", "same_tier", "view_file"]


def window_control(msg: dict, stage, ctx) -> None:
    """The window's mouse and wheel, as control messages: the same path as Python's."""
    try:
        steer(msg, stage, ctx)
    except ControlError as exc:  # e.g. a turn before anything was framed
        ctx.log.debug("window: %s", exc)


def view_file(ctx) -> Optional[str]:
    d = getattr(ctx.info, "run_dir", None)
    return os.path.join(d, "view-state.json") if d else None


def keep(ctx, view: ViewController) -> None:
    """Write the view where a restarted render stage finds it (the private run directory)."""
    path = view_file(ctx)
    if not path:
        return
    try:
        tmp = path + ".tmp"
        with open(tmp, "w") as f:
            json.dump({"state": view.state.to_dict(), "user_camera": view.user_camera}, f)
        os.replace(tmp, path)
    except OSError as exc:  # the view still works; only a restart would forget it
        ctx.log.warning("could not keep the view state for a restart: %s", exc)


def restore(ctx, view: ViewController, stage) -> None:
    """A restarted render stage takes up the view its predecessor had (camera, style, hidden)."""
    path = view_file(ctx)
    if not path or not os.path.exists(path):
        return
    try:
        with open(path) as f:
            d = json.load(f)
        s = d["state"]
        state = ViewState(camera=protocol.CameraState(**s["camera"]), style=protocol.StyleState(**s["style"]),
                          hidden_sources=list(s.get("hidden_sources", [])), version=int(s["version"]))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        ctx.log.warning("the kept view state is unreadable (%s); starting from the config", exc)
        return
    view.state, view.user_camera = state, bool(d.get("user_camera"))
    r = stage.renderer
    new_cfg = style_render_config(r.cfg, state.style)
    if not r.restyle(new_cfg):
        nr = same_tier(r, new_cfg, stage)
        r.close()
        stage.renderer = nr
        stage.full_upload = True
    ctx.log.info("view state of the previous render stage taken up (version %d)", state.version)


def same_tier(r: Renderer, new_cfg, stage) -> Renderer:
    """A new renderer of ``r``'s tier with another style; a compile still due carries over
    (the raster switch reads ``compiled_pending``)."""
    nr = type(r)(new_cfg, stage.capacity, stage.channels)
    if getattr(r, "compiled_pending", None) is not None:
        nr.compiled_pending = r.compiled_pending  # type: ignore[attr-defined]
    return nr


def steer(req: dict, stage, ctx) -> dict:
    """Apply a control message to the main view (the one path of the window, Python's
    ``Pipeline.view`` and the style every view shares): checked once by
    :func:`~pointflow.render.view.protocol.apply`; a new style goes to the renderer (in place,
    or a new renderer of the same tier when the tier caches it); the state is kept for a
    restarted render stage. Returns the reply (raises ControlError)."""
    view = stage.view
    old = view.state
    view.apply(req, stage.window)
    if view.state.style != old.style:
        r = stage.renderer
        new_cfg = style_render_config(r.cfg, view.state.style)
        if not r.restyle(new_cfg):
            try:
                nr = same_tier(r, new_cfg, stage)
            except Exception as exc:  # noqa: BLE001 - keep drawing with the old style
                view.state = old
                raise ControlError("style", f"the {r.tier} tier could not take the new style: {exc}") from None
            r.close()
            stage.renderer = nr
            stage.full_upload = True
            if stage.window is not None:
                stage.window.renderer = nr
            ctx.counters.extra["tier_info"] = nr.info()
            ctx.log.info("new %s renderer for the style %s", nr.tier, dataclasses.asdict(view.state.style))
    if view.state.version != old.version:
        ctx.counters.extra["view_version"] = view.state.version
        keep(ctx, view)
    return view.reply(stage.window, stage.frames)
