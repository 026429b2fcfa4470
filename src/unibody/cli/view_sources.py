"""What ``unibody view`` shows of each file: bodies posed by ``BodyLayer``, marker takes.

The viewer (:mod:`unibody.viz.viewer`) sits below the body on the floors and takes plain
arrays; this module, on the command's floor, turns files into its :class:`SceneItem` s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..motion import MAX_DISTANCE
from ..viz.viewer.tracks import GHOST, LABELLED, UNLABELLED, IdentityControls, MarkerTrack, SceneItem
from ._common import InputError, UsageError, _about, _read, _read_take

__all__ = ["LayerBody", "default_body", "load_item", "panoman_item", "resolved_item"]

_CHUNK = 16  # frames posed together: batch posing costs ~7x less per frame than one at a time
_PCA_SLIDERS = 10  # leading PCA components that get a slider
_ANNY_DEFAULT = (0.5, 0.5, 0.5, 0.5, 0.5, 0.5)


class LayerBody:
    """A :class:`~unibody.viz.viewer.tracks.BodySource` posing a motion with a ``BodyLayer``.

    Frames are posed ``_CHUNK`` at a time and the last chunk is kept, so playback poses in
    batches and scrubbing back and forth within a chunk poses nothing.
    """

    def __init__(
        self,
        name: str,
        layer,
        params: np.ndarray,
        pose: np.ndarray,
        transl: np.ndarray,
        fps: float,
        controls: IdentityControls | None,
    ) -> None:
        self.name = name
        self.layer = layer
        self.faces = layer.faces.numpy().astype(np.uint32)
        self.joint_names = tuple(layer.joint_names)
        self.parents = tuple(int(p) for p in layer.rig_tree.parents)
        self.num_frames = int(pose.shape[0])
        self.fps = float(fps)
        self.identity = controls
        self._pose = torch.as_tensor(np.asarray(pose, np.float32))
        self._transl = torch.as_tensor(np.asarray(transl, np.float32))
        self._params = torch.as_tensor(np.asarray(params, np.float32)).reshape(1, -1).clone()
        self._edits: dict[int, torch.Tensor] = {}
        self._prepared = None
        self._chunk: tuple[int, np.ndarray, np.ndarray] | None = None

    def _prepare(self):
        if self._prepared is None:
            with torch.no_grad():
                self._prepared = self.layer.prepare_identity(self._params)
        return self._prepared

    def _posed(self, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        from ..geometry.rotations import axis_angle_to_matrix

        pose = self._pose[start:stop]
        if self._edits:
            pose = axis_angle_to_matrix(pose)
            for joint, rot in self._edits.items():
                pose[:, joint - 1] = pose[:, joint - 1] @ rot
        with torch.no_grad():
            out = self.layer.pose(self._prepare(), pose, transl=self._transl[start:stop])
        return out.vertices.contiguous().numpy(), out.joints.numpy()

    def frames(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        index = np.asarray(index, dtype=np.int64)
        if index.size and (index.min() < 0 or index.max() >= self.num_frames):
            raise ValueError(f"index: expected frames in [0, {self.num_frames}), got {index.min()}..{index.max()}")
        verts = np.empty((len(index), self.layer.num_vertices, 3), np.float32)
        joints = np.empty((len(index), self.layer.num_joints, 3), np.float32)
        for n, k in enumerate(index):
            start = (int(k) // _CHUNK) * _CHUNK
            if self._chunk is None or self._chunk[0] != start:
                self._chunk = (start, *self._posed(start, min(start + _CHUNK, self.num_frames)))
            verts[n], joints[n] = self._chunk[1][k - start], self._chunk[2][k - start]
        return verts, joints

    def set_identity(self, values: np.ndarray) -> None:
        if self.identity is None:
            return
        values = np.asarray(values, np.float32)
        self._params[0, : len(values)] = torch.from_numpy(values)
        self._prepared, self._chunk = None, None

    def set_joint_rotation(self, joint: int, axis_angle: np.ndarray) -> None:
        """Turn ``joint`` (1..77) by ``axis_angle`` (3,) radians in its own frame, on every frame."""
        from ..geometry.rotations import axis_angle_to_matrix

        if not 1 <= joint < len(self.joint_names):
            raise ValueError(f"joint: expected 1..{len(self.joint_names) - 1}, got {joint}")
        aa = torch.as_tensor(np.asarray(axis_angle, np.float32)).reshape(3)
        if float(aa.norm()) == 0.0:
            self._edits.pop(joint, None)
        else:
            self._edits[joint] = axis_angle_to_matrix(aa)
        self._chunk = None


def resolved_item(item: SceneItem, progress=None) -> SceneItem | None:
    """``item``'s posed bodies with every frame moved out of self-intersection, or None if it has none.

    :func:`unibody.occupancy.resolve_self_intersections` (the shipped occupancy network; about
    a second a frame on one core), 32 frames at a time.
    """
    from ..occupancy import BodyOccupancy, resolve_self_intersections

    bodies = [b for b in item.bodies if isinstance(b, LayerBody)]
    if not bodies:
        return None
    occupancy = BodyOccupancy.pretrained()
    out = []
    for body in bodies:
        poses = []
        for start in range(0, body.num_frames, 32):
            stop = min(start + 32, body.num_frames)
            if progress is not None:
                progress(f"resolving self-intersections of {body.name}: frames {start}-{stop - 1} of {body.num_frames}")
            params = body._params.expand(stop - start, -1)
            pose, transl = body._pose[start:stop], body._transl[start:stop]
            fixed = resolve_self_intersections(occupancy, body.layer, params, pose, transl=transl)
            poses.append(fixed.pose.detach())
        pose = torch.cat(poses).numpy()
        name = f"{body.name} (resolved)"
        params = body._params[0].numpy()
        out.append(LayerBody(name, body.layer, params, pose, body._transl.numpy(), body.fps, body.identity))
    return SceneItem(f"{item.name} (resolved)", bodies=tuple(out))


def panoman_item(item: SceneItem, frame: int, progress=None) -> SceneItem | None:
    """A PanoMan fit (paper 004) of ``item``'s first posed body at ``frame``, with its constraints.

    The constraints are the ones of ``docs/panoman.md``: 21 surface handles (every 900th
    vertex) and the 77 joints regressed from the body; the fit starts from the unified body's
    LBS fit (:func:`~unibody.panoman.fit_body`) and runs the shell solve
    (:func:`~unibody.panoman.fit`). The handles are drawn as markers ``h0``... with their
    residual to the fitted mesh. About 20 s on one core. None when the item has no posed body.
    """
    from ..body import BodyLayer
    from ..panoman import Handles, PanoMan, fit, fit_body, regressor_matrix

    body = next((b for b in item.bodies if isinstance(b, LayerBody)), None)
    if body is None:
        return None
    if not 0 <= frame < body.num_frames:
        raise UsageError(f"--panoman: expected a frame in 0..{body.num_frames - 1} of {item.name}, got {frame}")
    if progress is not None:
        progress(f"fitting PanoMan to {body.name}, frame {frame}")
    target = torch.from_numpy(body.frames(np.array([frame]))[0][0]).double()
    model = PanoMan.load()
    layer = BodyLayer.from_pca(num_components=10, dtype=torch.float64)
    ids, w = model.joint_regressor
    joints = (target[ids] * w[..., None].double()).sum(1)  # (77, 3)
    handles = torch.arange(0, target.shape[0], 900)
    points = target[handles]
    lbs = fit_body(layer, handles, points[None], regressor_matrix(ids, w, target.shape[0]), joints[None])
    result = fit(model, lbs.shape[0], Handles(handles.numpy(), points.numpy()), reference=lbs.vertices[0].detach())
    verts = np.asarray(result.vertices, np.float32)
    name = f"{body.name} frame {frame} (PanoMan fit)"
    fitted = MeshSequenceBody(name, verts[None], body.faces, body.fps)
    pts = points.numpy().astype(np.float32)
    residual = np.linalg.norm(verts[handles.numpy()] - pts, axis=1)[None]
    labels = tuple(f"h{i}" for i in range(len(pts)))
    track = MarkerTrack(name, pts[None], labels, np.full((1, len(pts)), LABELLED), body.fps, residual)
    return SceneItem(name, bodies=(fitted,), markers=(track,))


def _layer(backend: str, num_params: int | None):
    from ..body import BodyLayer

    if backend == "pca":
        return BodyLayer.from_pca(num_components=num_params or 128)
    return BodyLayer.from_anny()


def _controls(layer, backend: str, params: np.ndarray) -> IdentityControls:
    if backend == "pca":
        n = min(_PCA_SLIDERS, len(params))
        bound = layer.identity.param_bound[:n].numpy().astype(np.float64)
        lim = np.minimum(3.0, bound)
        low = np.minimum(-lim, params[:n])
        high = np.maximum(lim, params[:n])
        return IdentityControls("pca", tuple(layer.identity.param_names[:n]), low, high, params[:n])
    names = tuple(layer.identity.param_names)
    return IdentityControls("anny", names, np.zeros(len(names)), np.ones(len(names)), params)


def body_from_motion(name: str, motion, layers: dict) -> LayerBody:
    """A :class:`LayerBody` replaying ``motion`` (its own identity; Anny's average without one)."""
    backend = motion.identity_backend or "anny"
    if motion.identity is not None and backend not in ("anny", "pca"):
        raise InputError(f"{name}: identity_backend: the viewer replays 'anny' and 'pca' identities, got {backend!r}")
    if motion.identity is None:
        backend, params = "anny", np.array(_ANNY_DEFAULT, np.float32)
    else:
        params = np.asarray(motion.identity, np.float32)
    key = (backend, len(params) if backend == "pca" else None)
    if key not in layers:
        layers[key] = _layer(*key)
    layer = layers[key]
    return LayerBody(name, layer, params, motion.pose, motion.transl, motion.fps, _controls(layer, backend, params))


def default_body(backend: str, layers: dict, params: np.ndarray | None = None) -> SceneItem:
    """One body of ``backend`` (``anny`` or ``pca``) in the T-pose, for the identity and pose panels.

    ``params``: its identity (default: Anny's average phenotypes, or the PCA mean).
    """
    if backend not in ("anny", "pca"):
        raise InputError(f"--body: expected anny or pca, got {backend!r}")
    key = (backend, None)
    if key not in layers:
        layers[key] = _layer(backend, None)
    layer = layers[key]
    if params is None:
        params = _ANNY_DEFAULT if backend == "anny" else np.zeros(layer.identity.num_params)
    params = np.asarray(params, np.float32)
    pose, transl = np.zeros((1, 77, 3), np.float32), np.array([[0.0, 0.95, 0.0]], np.float32)
    body = LayerBody(backend, layer, params, pose, transl, 30.0, _controls(layer, backend, params))
    return SceneItem(backend, bodies=(body,))


def _marker_kinds(points: np.ndarray, labels: tuple[str, ...]) -> np.ndarray:
    """(T, M) kinds: named markers, ``*n`` points near the subject, points away from it.

    Away: an unlabelled point past 1.2 m from its frame's main cluster, a labelled one past
    ``FAR_RADIUS`` (2 m, the labeler's rule: a glitch, not a body part), any point past
    ``MAX_DISTANCE`` from the origin. The viewer does not frame its camera on them.
    """
    from ..mocap.pipeline import FAR_RADIUS, main_cluster

    with np.errstate(invalid="ignore"):
        sane = (np.abs(points) <= MAX_DISTANCE).all(2)  # a point at 1e30 m is never framed, even alone
    near = main_cluster(points, radius=1.2) & sane
    within = main_cluster(points, radius=FAR_RADIUS) & sane
    starred = np.array([x.startswith("*") for x in labels], dtype=bool)
    kinds = np.where(within, LABELLED, GHOST).astype(np.uint8)
    kinds[:, starred] = np.where(near[:, starred], UNLABELLED, GHOST)
    return kinds


def marker_item(path: Path, layers: dict, solve: str | None, up: str) -> SceneItem:
    """A C3D (or marker npz) take as a :class:`MarkerTrack`, with its solved body if ``solve`` names a layout."""
    from ..mocap.frames import lab_to_unibody

    seq = _read_take(path, up)
    if seq.num_frames == 0 or seq.num_markers == 0:
        raise InputError(f"{path}: no marker samples (frames {seq.num_frames}, markers {seq.num_markers})")
    points = lab_to_unibody(seq.points, up=up).astype(np.float32)
    with np.errstate(invalid="ignore"):
        shown = (np.abs(points) <= MAX_DISTANCE).all(2)  # NaN (missing) and absurd points are not
    if not shown.any():
        raise InputError(
            f"{path}: no marker is visible within {MAX_DISTANCE:g} m of the origin "
            f"in any of its {seq.num_frames} frames"
        )
    labels = seq.qualified_labels
    residual = None
    bodies: tuple = ()
    if solve is not None:
        from ..mocap.layout import MarkerLayout
        from ..mocap.pipeline import solve_sequence

        try:
            layout = MarkerLayout.load(solve)
        except (ValueError, OSError) as err:
            raise UsageError(f"--solve: {err}") from None
        with _about(path):
            result = solve_sequence(seq, layout, up=up)
        motion = result.to_motion(seq.rate)
        bodies = (body_from_motion(f"{path.name} (solved)", motion, layers),)
        residual = np.full(points.shape[:2], np.nan, np.float32)
        present = [x for x in layout.labels if x in seq.labels]
        cols = [seq.labels.index(x) for x in present]
        residual[:, cols] = result.residual.numpy()[:, : len(cols)]
    track = MarkerTrack(path.name, points, labels, _marker_kinds(points, labels), seq.rate, residual)
    return SceneItem(path.name, bodies=bodies, markers=(track,))


def _mesh_item(path: Path, layers: dict) -> SceneItem:
    from ..motion import load_mesh_sequence

    seq = _read(path, load_mesh_sequence)
    with np.load(path, allow_pickle=False) as data:
        faces = data["faces"] if "faces" in data.files else None
    if faces is None:
        if seq.topology != "canonical":
            raise InputError(f"{path}: a {seq.topology!r} mesh sequence without a faces field; the viewer needs faces")
        key = ("pca", None)
        if key not in layers:
            layers[key] = _layer("pca", None)
        faces = layers[key].faces.numpy()
    return SceneItem(path.name, bodies=(MeshSequenceBody(path.name, seq.vertices, faces, seq.fps or 30.0),))


def _glb_item(path: Path) -> SceneItem:
    """A GLB: its bytes for the browser, and its scene's triangle meshes for the recorder.

    The meshes stand as a glTF viewer shows the file before it plays: placed by the nodes' own
    transforms, skins applied (:func:`unibody.io.glb_scene.read_glb_scene`). A file that cannot
    be read this way, or holds no triangle, is refused here, so a broken file never reaches the
    browser as an empty scene.
    """
    from ..io.glb_scene import read_glb_scene

    data = path.read_bytes()
    if data[:4] != b"glTF":
        raise InputError(f"{path}: not a binary glTF file (starts with {data[:4]!r}, expected b'glTF')")
    try:
        still = tuple(read_glb_scene(data))
    except ValueError as exc:
        raise InputError(f"{path}: not a glTF file the viewer reads ({str(exc)[:200]})") from None
    if not still:
        raise InputError(f"{path}: no triangle mesh in the file's scene")
    far = max(float(np.abs(v).max()) if np.isfinite(v).all() else np.inf for v, _ in still)
    if far > MAX_DISTANCE:
        raise InputError(
            f"{path}: vertices: expected finite positions within {MAX_DISTANCE:g} m of the origin (metres), "
            f"got {far:.3g}"
        )
    return SceneItem(path.name, glb=data, still=still)


class MeshSequenceBody:
    """A :class:`~unibody.viz.viewer.tracks.BodySource` of stored meshes (no joints, no editing)."""

    def __init__(self, name: str, vertices: np.ndarray, faces: np.ndarray, fps: float) -> None:
        self.name, self.fps = name, float(fps)
        self._vertices = np.asarray(vertices, np.float32)
        faces = np.asarray(faces)
        n = self._vertices.shape[1]
        if faces.ndim != 2 or faces.shape[1] != 3 or not len(faces) or faces.dtype.kind not in "iu":
            raise InputError(f"{name}: faces: expected (F, 3) integer indices, F >= 1, got {faces.shape} {faces.dtype}")
        if faces.min() < 0 or faces.max() >= n:
            raise InputError(f"{name}: faces: expected indices in 0..{n - 1}, got {faces.min()}..{faces.max()}")
        self.faces = faces.astype(np.uint32)
        self.num_frames = self._vertices.shape[0]
        self.joint_names, self.parents, self.identity = ("Root",), (-1,), None

    def frames(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        v = self._vertices[np.asarray(index, np.int64)]
        return v, np.zeros((len(v), 1, 3), np.float32)

    def set_identity(self, values: np.ndarray) -> None:
        pass

    def set_joint_rotation(self, joint: int, axis_angle: np.ndarray) -> None:
        pass


def load_item(path: Path, layers: dict, *, solve: str | None = None, up: str = "z") -> SceneItem:
    """The :class:`SceneItem` of one file: motion formats, mesh sequences, C3D/marker npz, GLB.

    Raises:
        InputError: the file cannot be read (one line naming it).
    """
    from ..convert._types import ConvertOptions
    from ..convert.formats import NotAMotion, detect, reader

    if not path.is_file():
        raise InputError(f"{path}: no such file" if not path.exists() else f"{path}: is not a file")
    suffix = path.suffix.lower()
    if suffix in (".c3d", ".trc"):
        return marker_item(path, layers, solve, up)
    if suffix == ".glb":
        return _glb_item(path)
    fmt = _read(path, detect) if suffix != ".npz" or not _is_markers(path) else "markers"
    if fmt == "markers":
        return marker_item(path, layers, solve, up)
    if fmt == "meshes":
        return _mesh_item(path, layers)
    try:
        converted = _read(path, reader(fmt), ConvertOptions())
    except NotAMotion as exc:
        raise InputError(str(exc)) from None
    motion = converted.motion
    if len(motion.pose) == 0:
        raise InputError(f"{path}: pose: expected at least one frame, got shape {motion.pose.shape}")
    return SceneItem(path.name, bodies=(body_from_motion(path.name, motion, layers),))


def _is_markers(path: Path) -> bool:
    """Whether an npz is a marker file of ``unibody mocap label`` (points, labels)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return {"points", "labels"} <= set(data.files)
    except Exception:  # noqa: BLE001 - not readable as npz: let the format reader say why
        return False
