"""Optical motion capture: read markers, label raw point clouds, solve the unified body (paper 003).

Modules: :mod:`~unibody.mocap.c3d` (C3D / npz marker files), :mod:`~unibody.mocap.layout`
(named markers on the canonical mesh), :mod:`~unibody.mocap.synthetic` (synthetic training
mocap), :mod:`~unibody.mocap.corrupt` (occlusions, ghosts, broken trajectories),
:mod:`~unibody.mocap.labeler` (self-attention + Sinkhorn labeler), :mod:`~unibody.mocap.tracklets`,
:mod:`~unibody.mocap.metrics`, :mod:`~unibody.mocap.solve` (MoSh-like body solve).
"""
