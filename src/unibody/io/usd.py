"""UsdSkel export of a skinned, animated mesh (``usd-core``, the optional extra ``unibody[usd]``).

Stage layout (metres: ``metersPerUnit`` 1, ``upAxis`` Y; ``defaultPrim`` the SkelRoot)::

    /Body               SkelRoot
    /Body/Skeleton      Skeleton: joints (paths of the hierarchy, "Root/Hips/Spine1", ...),
                        bindTransforms (world, the mesh's pose), restTransforms (local, frame 0);
                        skel:animationSource -> /Body/Motion
    /Body/Motion        SkelAnimation: per time code i (frame i), rotations (quatf) and
                        translations (float3) of every joint; scales (half3) constant 1
    /Body/Mesh          Mesh: points, faceVertexCounts/Indices, vertex normals, extent;
                        primvars:skel:jointIndices / jointWeights (vertex, elementSize K),
                        skel:geomBindTransform (identity), skel:skeleton -> /Body/Skeleton

``timeCodesPerSecond`` = ``framesPerSecond`` = fps, time codes 0 .. T-1. USD matrices are
row-vector (the transpose of the column-vector ones used everywhere else in unibody).
The file format follows the suffix: ``.usda`` text, ``.usdc`` or ``.usd`` binary crate.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .glb import SkinnedAnimation, vertex_normals

__all__ = ["USD_SUFFIXES", "write_skinned_usd"]

USD_SUFFIXES = (".usda", ".usdc", ".usd")


def _pxr():
    """The pxr modules, or ImportError with the one-line install command."""
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt
    except ImportError:
        raise ImportError("USD export needs usd-core: pip install 'unibody[usd]'") from None
    return Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt


def _joint_paths(names: tuple[str, ...], parents: np.ndarray) -> list[str]:
    """UsdSkel joint tokens: each joint's path from its root, e.g. ``Root/Hips/Spine1``."""
    paths: list[str] = []
    for name, p in zip(names, parents.tolist(), strict=True):
        paths.append(name if p < 0 else f"{paths[p]}/{name}")
    return paths


def write_skinned_usd(path: str | os.PathLike[str], animation: SkinnedAnimation) -> None:
    """Write ``animation`` as a UsdSkel stage at exactly ``path`` (atomically; format by suffix).

    Raises:
        ValueError: ``path`` does not end in .usda, .usdc or .usd, or ``animation`` is not a
            SkinnedAnimation; or a joint name is not a valid USD identifier.
        ImportError: ``usd-core`` is not installed.
    """
    path = Path(path)
    if path.suffix.lower() not in USD_SUFFIXES:
        raise ValueError(f"path: expected a {' or '.join(USD_SUFFIXES)} file, got {str(path)!r}")
    if not isinstance(animation, SkinnedAnimation):
        raise ValueError(f"animation: expected a SkinnedAnimation, got {type(animation).__name__}")
    Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    a = animation
    bad = [n for n in a.joint_names if not Sdf.Path.IsValidIdentifier(n)]
    if bad:
        raise ValueError(f"animation.joint_names: expected USD identifiers, got {bad[0]!r}")
    j, t = len(a.joint_names), a.num_frames

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, UsdGeom.LinearUnits.meters)
    stage.SetTimeCodesPerSecond(a.fps)
    stage.SetFramesPerSecond(a.fps)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(t - 1)
    root = UsdSkel.Root.Define(stage, "/Body")
    stage.SetDefaultPrim(root.GetPrim())

    tokens = _joint_paths(a.joint_names, a.parents)
    skel = UsdSkel.Skeleton.Define(stage, "/Body/Skeleton")
    skel.CreateJointsAttr(tokens)
    skel.CreateJointNamesAttr(list(a.joint_names))
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(a.bind_matrices.transpose(0, 2, 1))))
    parent_bind = a.bind_matrices[np.maximum(a.parents, 0)]
    rest = np.where((a.parents < 0)[:, None, None], a.bind_matrices, np.linalg.solve(parent_bind, a.bind_matrices))
    rest[:, 3] = (0.0, 0.0, 0.0, 1.0)
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(rest.transpose(0, 2, 1))))

    anim = UsdSkel.Animation.Define(stage, "/Body/Motion")
    anim.CreateJointsAttr(tokens)
    anim.CreateScalesAttr(Vt.Vec3hArray(j, Gf.Vec3h(1.0, 1.0, 1.0)))
    rot_attr, trans_attr = anim.CreateRotationsAttr(), anim.CreateTranslationsAttr()
    quats = np.ascontiguousarray(a.unit_quaternions(), dtype=np.float32)  # Gf.Quatf stores (x, y, z, w)
    trans = np.ascontiguousarray(a.translations, dtype=np.float32)
    for i in range(t):
        rot_attr.Set(Vt.QuatfArray.FromNumpy(quats[i]), Usd.TimeCode(i))
        trans_attr.Set(Vt.Vec3fArray.FromNumpy(trans[i]), Usd.TimeCode(i))
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])

    mesh = UsdGeom.Mesh.Define(stage, "/Body/Mesh")
    points = a.vertices.astype(np.float32)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(a.faces), 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(a.faces.astype(np.int32).ravel()))
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(vertex_normals(a.vertices, a.faces).astype(np.float32)))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([points.min(0), points.max(0)])))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    k = a.joint_indices.shape[1]
    weights = a.normalized_weights()
    indices = np.where(weights > 0, a.joint_indices, 0).astype(np.int32)
    binding.CreateJointIndicesPrimvar(False, k).Set(Vt.IntArray.FromNumpy(indices.ravel()))
    binding.CreateJointWeightsPrimvar(False, k).Set(Vt.FloatArray.FromNumpy(weights.ravel()))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))

    with atomic_path(path) as tmp:  # the temporary name keeps the suffix: it picks the format
        if not stage.GetRootLayer().Export(str(tmp)):
            raise OSError(f"{path}: USD could not write the layer")
