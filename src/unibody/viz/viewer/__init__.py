"""``unibody view``: an interactive viewer for bodies, motions and mocap takes (viser, optional).

Needs the ``viewer`` extra (``pip install 'unibody[viewer]'``); importing this package without
viser works, making a :class:`Viewer` raises ImportError with the install line. Offscreen
pictures and videos (:mod:`unibody.viz.viewer.record`) need only numpy and Pillow (and
imageio-ffmpeg for ``.mp4``).
"""

from __future__ import annotations

from .tracks import (
    GHOST,
    GHOST_COLOR,
    LABELLED,
    UNLABELLED,
    UNLABELLED_COLOR,
    BodySource,
    IdentityControls,
    MarkerTrack,
    SceneItem,
    marker_color,
    marker_colors,
)

__all__ = [
    "GHOST",
    "GHOST_COLOR",
    "LABELLED",
    "UNLABELLED",
    "UNLABELLED_COLOR",
    "BodySource",
    "IdentityControls",
    "MarkerTrack",
    "SceneItem",
    "Viewer",
    "marker_color",
    "marker_colors",
    "viser_missing",
]


def viser_missing() -> str | None:
    """Why the interactive viewer cannot start here (viser not installed), or None."""
    import importlib.util

    if importlib.util.find_spec("viser") is None:
        return "the viewer needs viser: pip install 'unibody[viewer]'"
    return None


def __getattr__(name: str):
    if name == "Viewer":
        if (why := viser_missing()) is not None:
            raise ImportError(why)
        from .app import Viewer

        return Viewer
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
