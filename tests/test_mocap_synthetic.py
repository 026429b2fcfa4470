"""Marker layouts, the pose generator and synthetic mocap: placement, statistics, exactness."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch

from unibody.geometry.rotations import axis_angle_to_matrix
from unibody.mocap.layout import MarkerLayout, available_layouts, place_markers, vertex_normals
from unibody.mocap.synthetic import POSE, SyntheticConfig, SyntheticMocap
from unibody.rig import joint_index
from unibody.synth.poses import sample_poses


def test_shipped_layouts():
    assert {"pig35", "pig39", "cmu41", "superset"} <= set(available_layouts())
    sizes = {name: len(MarkerLayout.load(name)) for name in ("pig35", "pig39", "cmu41")}
    assert sizes == {"pig35": 35, "pig39": 39, "cmu41": 41}
    sup = MarkerLayout.load("superset")
    for name in ("pig39", "cmu41"):
        lay = MarkerLayout.load(name)
        shared = [x for x in lay.labels if x in sup.labels]
        assert torch.equal(sup.subset(shared).vertices, lay.subset(shared).vertices)
    assert set(MarkerLayout.load("pig35").labels) < set(MarkerLayout.load("pig39").labels)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: "{oops", r"x.json: not a layout JSON file \(Expecting property name .* at line 1 column 2\)"),
        (lambda d: [1, 2], r"x.json: expected a layout \(format 'unibody.marker_layout/1'\), got 'a JSON list'"),
        (lambda d: d.pop("markers") and d, r"x.json: markers: expected an object of one or more markers, got None"),
        (lambda d: d.pop("name") and d, r"x.json: name: expected a non-empty string, got None"),
        (lambda d: d | {"topology": "smplx"}, r"x.json: topology: expected 'canonical', got 'smplx'"),
        (lambda d: d["markers"]["LFHD"].update(vertex=10**9) or d, r"markers.LFHD.vertex: .* 0..18055, got 1000000000"),
        (lambda d: d["markers"]["LFHD"].update(vertex=-5) or d, r"markers.LFHD.vertex: .*, got -5"),
        (lambda d: d["markers"]["LFHD"].update(vertex=1.7) or d, r"markers.LFHD.vertex: .*, got 1.7"),
        (
            lambda d: d["markers"]["LFHD"].update(distance=1e30) or d,
            r"LFHD.distance: .* \+-0.2, got 1e\+30",
        ),
        (lambda d: d["markers"]["LFHD"].update(distance=None) or d, r"markers.LFHD.distance: .*, got None"),
        (
            lambda d: d["markers"].update(LFHD=5) or d,
            r"markers.LFHD: expected an object with vertex .*, got 5",
        ),
        (lambda d: d["markers"].update({"*1": d["markers"]["LFHD"]}) or d, r"x.json: labels: .* got '\*1'"),
    ],
)
def test_layout_files_are_checked_field_by_field(tmp_path, edit, message):
    # were: internal errors (KeyError, IndexError, a failed SVD), messages without the file, or
    # layouts used as they were (vertex -5 is vertex 18051; a marker 1e30 m off the skin)
    data = MarkerLayout.load("cmu41").to_json()
    changed = edit(data)
    (tmp_path / "x.json").write_text(changed if isinstance(changed, str) else json.dumps(changed))
    with pytest.raises(ValueError, match=message):
        MarkerLayout.load(tmp_path / "x.json")
    (tmp_path / "x.json").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ValueError, match=r"x.json: not a layout JSON file \(not UTF-8 text\)"):
        MarkerLayout.load(tmp_path / "x.json")


def test_layout_json_round_trip(tmp_path):
    lay = MarkerLayout.load("cmu41")
    lay.save(tmp_path / "x.json")
    back = MarkerLayout.load(tmp_path / "x.json")
    assert back.labels == lay.labels and torch.equal(back.vertices, lay.vertices)
    assert torch.allclose(back.distance, lay.distance)
    with pytest.raises(ValueError, match="unknown layout"):
        MarkerLayout.load("nope")
    with pytest.raises(ValueError, match="duplicate"):
        MarkerLayout("x", ("A", "A"), torch.tensor([0, 1]), torch.zeros(2))
    with pytest.raises(ValueError, match="not in layout"):
        lay.index("XYZ")


def test_layout_is_anatomical(body_pca_mean):
    """Left markers lie on the body's left (+X), mirrored pairs are symmetric, heights are ordered."""
    v = body_pca_mean
    lay = MarkerLayout.load("superset")
    p = {x: v[i] for x, i in zip(lay.labels, lay.vertices, strict=True)}
    for x in lay.labels:
        if x[0] == "L" and "R" + x[1:] in p:
            assert p[x][0] > 0.02 and p["R" + x[1:]][0] < -0.02, x
            mirrored = p["R" + x[1:]] * torch.tensor([-1.0, 1.0, 1.0])
            assert (p[x] - mirrored).norm() < 0.02, x
    order = ["LHEE", "LANK", "LKNE", "LTHI", "LASI", "STRN", "CLAV", "LFHD"]
    heights = [float(p[x][1]) for x in order]
    assert heights == sorted(heights)
    assert p["STRN"][2] > 0.05 and p["T10"][2] < -0.05  # front / back
    # front head markers on the temples (head bands), back waist markers over the PSIS dimples
    assert 0.10 < float((p["LFHD"] - p["RFHD"]).norm()) < 0.16
    assert 0.07 < float((p["LBWT"] - p["RBWT"]).norm()) < 0.13


@pytest.fixture(scope="module")
def body_pca_mean():
    from unibody.body import BodyLayer

    layer = BodyLayer.from_pca(num_components=1)
    out = layer(torch.zeros(1, 1), torch.zeros(1, 77, 3))
    return out.vertices[0]


def test_place_markers_offsets_along_normals():
    v = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]]).double()
    f = torch.tensor([[0, 1, 2]])
    n = vertex_normals(v, f)
    assert torch.allclose(n, torch.tensor([0.0, 0.0, 1.0]).double().expand(1, 3, 3))
    m = place_markers(v, f, torch.tensor([1, 2]), torch.tensor([0.01, 0.02]))
    assert torch.allclose(m, torch.tensor([[[1.0, 0, 0.01], [0, 1, 0.02]]]).double())


def test_sample_poses_seeded_and_plausible():
    a = sample_poses(64, torch.Generator().manual_seed(0))
    b = sample_poses(64, torch.Generator().manual_seed(0))
    assert a.shape == (64, 77, 3) and torch.equal(a, b)
    assert torch.isfinite(a).all()
    knee = a[:, joint_index("LeftShin") - 1, 0]
    assert (knee >= -1e-6).all() and (knee <= 2.3 + 1e-6).all()  # knees never hyperextend
    # the right side mirrors the left's range: knee flexion is about +X on both sides
    assert (a[:, joint_index("RightShin") - 1, 0] >= -1e-6).all()
    assert a[:, joint_index("LeftEye") - 1].abs().max() == 0
    with pytest.raises(ValueError, match="tumble"):
        sample_poses(2, torch.Generator(), tumble=2.0)


def _exact(distance: float) -> SyntheticConfig:
    """No placement jitter, noise, spread or wrist bars: markers exactly ``distance`` off their vertex."""
    return SyntheticConfig(
        identities=8, jitter_radius=0.0, loose=(), segments=(), distance=(distance, distance), noise=(0.0, 0.0),
        spread=0.0, stick_prob=0.0,
    )  # fmt: skip


@pytest.fixture(scope="module")
def synthetic():
    return SyntheticMocap(MarkerLayout.load("pig39"), _exact(0.01))


def test_synthetic_markers_match_full_mesh(synthetic):
    """Skinning only the marker vertices equals posing the whole mesh (exact without skin offset)."""
    syn = synthetic
    cfg = _exact(0.0)
    syn0 = SyntheticMocap(syn.layout, cfg)
    g = torch.Generator().manual_seed(5)
    m = syn0.markers(4, g)
    g = torch.Generator().manual_seed(5)
    ident = torch.randint(8, (4,), generator=g)
    pose = sample_poses(4, g, **cfg.pose)
    out = syn0.layer(syn0.coefficients[ident], pose)
    ref = place_markers(out.vertices, syn0.layer.faces, syn0.layout.vertices, torch.zeros(len(syn0.layout)))
    assert (ref - m).abs().max() < 1e-4
    # with a skin offset the markers sit that far from their vertex, off the skin
    m1 = syn.markers(4, torch.Generator().manual_seed(5))
    assert torch.allclose((m1 - m).norm(dim=-1), torch.full((4, 39), 0.01), atol=1e-4)


def _hips_world(layer, pose: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) world rotation of the Hips of (B, 77, 3) poses."""
    o = layer.tpose_orient
    return o[0].T @ axis_angle_to_matrix(pose[:, 0]) @ o[1]


def test_synthetic_motions_pose_a_fraction_of_the_samples_at_any_heading():
    """With ``motions``, a fraction ``motion_prob`` of the poses are motion frames: every joint but the
    Hips as in the frame, the Hips turned about the vertical only, to headings all around; the markers
    are those of the full mesh in those poses; without draws of their own when motion_prob is 0."""
    layout, cfg = MarkerLayout.load("cmu41"), _exact(0.0)
    motions = sample_poses(3, torch.Generator().manual_seed(99), bend=1.0, tumble=0.5)  # not the recipe's stream
    syn = SyntheticMocap(layout, replace(cfg, motion_prob=1.0), motions=motions.double())
    pose = syn.poses(400, torch.Generator().manual_seed(1))
    which = (pose[:, None, 1:] - motions[None, :, 1:]).abs().amax(dim=(2, 3)).argmin(1)
    assert (pose[:, 1:] - motions[which, 1:]).abs().max() < 1e-6 and set(which.tolist()) == {0, 1, 2}
    turn = _hips_world(syn.layer, pose) @ _hips_world(syn.layer, motions[which]).transpose(1, 2)
    up = torch.tensor([0.0, 1.0, 0.0])
    assert ((turn @ up) - up).abs().max() < 1e-5  # a turn about the vertical
    heading = torch.rad2deg(torch.atan2(turn[:, 0, 2], turn[:, 0, 0]))
    assert torch.histc(heading, bins=8, min=-180, max=180).min() > 25  # all around (50 per bin expected)
    # a third of the samples from the motions, the rest from sample_poses
    third = SyntheticMocap(layout, replace(cfg, motion_prob=1 / 3), motions=motions)
    pose = third.poses(900, torch.Generator().manual_seed(2))
    moved = (pose[:, None, 1:] - motions[None, :, 1:]).abs().amax(dim=(2, 3)).min(1).values < 1e-6
    assert 0.28 < float(moved.float().mean()) < 0.39, moved.float().mean()
    # the markers follow those poses (same stream as markers_and_extras: identity, then pose)
    g = torch.Generator().manual_seed(5)
    ident = torch.randint(8, (4,), generator=g)
    out = syn.layer(syn.coefficients[ident], syn.poses(4, g))
    ref = place_markers(out.vertices, syn.layer.faces, layout.vertices, torch.zeros(len(layout)))
    assert (ref - syn.markers(4, torch.Generator().manual_seed(5))).abs().max() < 1e-4
    # motion_prob 0 draws nothing more: the same batches as without motions
    plain, none = SyntheticMocap(layout, cfg), SyntheticMocap(layout, replace(cfg, motion_prob=0.0), motions=motions)
    a, b = (x.sample(16, torch.Generator().manual_seed(3)) for x in (plain, none))
    assert torch.equal(a.points, b.points) and torch.equal(a.labels, b.labels)
    for bad, match in (
        (motions[:, :76], r"motions: expected shape \(F, 77, 3\)"),
        (motions[:0], "motions: expected at least one frame"),
        (motions.clone().fill_(float("nan")), "motions: expected finite"),
    ):
        with pytest.raises(ValueError, match=match):
            SyntheticMocap(layout, cfg, motions=bad)
    with pytest.raises(ValueError, match="motion_prob: expected a probability in"):
        SyntheticMocap(layout, replace(cfg, motion_prob=1.5))


def test_synthetic_statures_follow_the_config():
    """Three quarters of the pool get a stature uniform in the adult range; the rest keep the
    N(0, 1) draw of the PCA, children and giants included."""
    syn = SyntheticMocap(MarkerLayout.load("cmu41"), SyntheticConfig(identities=400, pool_seed=3))
    with torch.no_grad():
        y = torch.cat([syn.layer.prepare_identity(c).rest_vertices[..., 1] for c in syn.coefficients.split(100)])
    h = y.amax(1) - y.amin(1)
    adult = ((h > 1.48) & (h < 1.97)).float().mean()
    assert 0.78 < adult < 0.92, adult  # 0.75 redrawn + the N(0, 1) draws that land there (~ 0.35 of 0.25)
    assert (h < 1.2).float().mean() > 0.03 and (h > 2.05).float().mean() > 0.01  # the others still span ages
    inside = h[(h > 1.48) & (h < 1.97)]
    assert abs(float(inside.mean()) - 1.725) < 0.03, inside.mean()  # uniform over the range
    free = SyntheticMocap(MarkerLayout.load("cmu41"), SyntheticConfig(identities=400, pool_seed=3, stature=None))
    assert torch.equal(free.coefficients, 1.0 * torch.randn(400, 16, generator=torch.Generator().manual_seed(3)))
    with pytest.raises(ValueError, match="stature"):
        SyntheticMocap(MarkerLayout.load("cmu41"), SyntheticConfig(identities=4, stature=(1.9, 1.5)))


def test_synthetic_jitter_and_subsets():
    lay = MarkerLayout.load("pig39")
    pig35 = MarkerLayout.load("pig35").labels
    cfg = SyntheticConfig(identities=4, subsets=(pig35,), subset_prob=0.5, noise=(0.0, 0.0))
    syn = SyntheticMocap(lay, cfg)
    radii = syn.jitter_radii()
    assert float(radii[lay.index("LKNE")]) == pytest.approx(cfg.jitter_radius)
    assert float(radii[lay.index("RTHI")]) == 0.0 and float(radii[lay.index("RBAK")]) == pytest.approx(0.08)
    assert float(radii[lay.index("LFHD")]) == pytest.approx(0.05)
    assert (syn.num_candidates > 1).all()
    rest_mean = syn.layer.identity(torch.zeros(1, 16))
    normal = vertex_normals(rest_mean, syn.layer.faces)[0]
    rest_mean = rest_mean[0]
    cand = syn.used[syn.candidates]  # (M, C) vertex ids
    for i in range(len(lay)):
        ids = cand[i, : syn.num_candidates[i]]
        if radii[i] > 0:  # markers placed by bone have radius 0
            assert (rest_mean[ids] - rest_mean[lay.vertices[i]]).norm(dim=-1).max() <= radii[i] + 1e-6
        assert (normal[ids] @ normal[lay.vertices[i]]).min() >= cfg.jitter_cos - 1e-6  # same side of the limb
    # a segment marker goes anywhere along its bone: RTHI from near the hip to near the knee
    thi = cand[lay.index("RTHI"), : syn.num_candidates[lay.index("RTHI")]]
    height = rest_mean[thi, 1]
    assert float(height.max() - height.min()) > 0.2
    assert (rest_mean[thi, 0] < -0.05).all()  # on the right leg, lateral
    m = syn.markers(2000, torch.Generator().manual_seed(0))
    extra = torch.tensor([x not in pig35 for x in lay.labels])
    dropped = m[:, extra].isnan().any(-1).all(-1).float().mean()
    assert abs(float(dropped) - 0.5) < 0.05
    assert not m[:, ~extra].isnan().any()


def test_synthetic_fitted_placement_keeps_each_marker_at_its_own_place():
    """A session layout (fitted to the session's frame): every marker, RTHI and the wrist bars
    included, within ``jitter_radius`` of its vertex and at its own layout distance (+-
    ``distance_jitter``), instead of the guides' slides and the shared distance range."""
    base = MarkerLayout.load("pig39")
    d = torch.linspace(0.004, 0.05, len(base))
    lay, flat = (MarkerLayout("session", base.labels, base.vertices, x) for x in (d, torch.zeros_like(d)))
    cfg = SyntheticConfig(identities=4, fitted=True, jitter_radius=0.02, distance_jitter=0.0, noise=(0.0, 0.0))
    syn, syn0 = SyntheticMocap(lay, cfg), SyntheticMocap(flat, cfg)
    assert torch.equal(syn.jitter_radii(), torch.full((len(lay),), 0.02)) and not syn.stick.any()
    rest_mean = syn.layer.identity(torch.zeros(1, 16))[0]
    cand = syn.used[syn.candidates]
    for i in range(len(lay)):
        ids = cand[i, : syn.num_candidates[i]]
        assert (rest_mean[ids] - rest_mean[lay.vertices[i]]).norm(dim=-1).max() <= 0.02 + 1e-6, lay.labels[i]
    m, m0 = (x.markers(64, torch.Generator().manual_seed(1)) for x in (syn, syn0))  # the same vertices
    assert torch.allclose((m - m0).norm(dim=-1), d.expand(64, -1), atol=1e-4)
    loose = SyntheticMocap(lay, SyntheticConfig(identities=4, fitted=True, distance_jitter=0.005, noise=(0.0, 0.0)))
    m1 = loose.markers(256, torch.Generator().manual_seed(1))
    m0 = SyntheticMocap(flat, replace(loose.config, distance_jitter=0.0)).markers(256, torch.Generator().manual_seed(1))
    off = (m1 - m0).norm(dim=-1) - d
    assert float(off.abs().max()) <= 0.005 + 1e-4 and float(off.std()) > 0.002  # uniform in +-5 mm
    rules = SyntheticMocap(lay, SyntheticConfig(identities=4))
    assert rules.num_candidates[lay.index("RTHI")] > 5 * syn.num_candidates[lay.index("RTHI")]  # the guide's slide


def test_synthetic_head_bands_follow_the_config():
    """Head-band markers go anywhere between their azimuths, on their side, near their height:
    the front pair 8-18 cm apart (5th-95th percentile; the evaluation files: 8.5-18.7), and never
    on the face or the back of the neck."""
    lay = MarkerLayout.load("pig39")
    bands = (("FHD", 10.0, 100.0), ("BHD", 110.0, 170.0))
    syn = SyntheticMocap(lay, SyntheticConfig(identities=16, bands=bands, noise=(0.0, 0.0)))
    assert float(syn.jitter_radii()[lay.index("LFHD")]) == 0.0
    rest = syn.layer.prepare_identity(torch.zeros(1, 16))
    head = rest.rest_vertices[0] - rest.rest_joints[0, syn.layer.joint_names.index("Head")]
    cand = syn.used[syn.candidates]
    for label, lo, hi in (("LFHD", 10, 100), ("RFHD", 10, 100), ("LBHD", 110, 170), ("RBHD", 110, 170)):
        i = lay.index(label)
        v = head[cand[i, : syn.num_candidates[i]]]
        side = 1.0 if label[0] == "L" else -1.0
        azimuth = torch.rad2deg(torch.atan2(side * v[:, 0], v[:, 2]))
        assert float(azimuth.min()) >= lo and float(azimuth.max()) <= hi, label
        assert float(azimuth.max() - azimuth.min()) > 0.6 * (hi - lo), label  # spread over the band
        assert float((v[:, 1] - head[lay.vertices[i], 1]).abs().max()) <= 0.025 + 1e-6
    m = syn.markers(2000, torch.Generator().manual_seed(0))
    front = (m[:, lay.index("LFHD")] - m[:, lay.index("RFHD")]).norm(dim=-1)
    lo, hi = torch.quantile(front, torch.tensor([0.05, 0.95]))
    assert 0.06 < float(lo) < 0.09 and 0.17 < float(hi) < 0.2, (lo, hi)


def test_synthetic_wrist_markers_sit_across_the_wrist():
    """WRA and WRB across the wrist (thumb and little-finger side): the elbow marker about as far
    from one as from the other (every evaluation file: within 2 cm; the 0.85-1.25 slide put WRB
    2.9 cm nearer), FIN on the back of the hand, 6.5-12 cm from WRA in the files (was 5.1)."""
    lay = MarkerLayout.load("cmu41")
    syn = SyntheticMocap(lay, SyntheticConfig(identities=32, stick_prob=0.0, noise=(0.0, 0.0)))
    m = syn.markers(2000, torch.Generator().manual_seed(0))

    def dist(a: str, b: str) -> torch.Tensor:
        return torch.cat([(m[:, lay.index(s + a)] - m[:, lay.index(s + b)]).norm(dim=-1) for s in "LR"])

    gap = dist("ELB", "WRA").median() - dist("ELB", "WRB").median()
    assert abs(float(gap)) < 0.02, gap
    assert 0.065 < float(dist("WRA", "FIN").median()) < 0.1
    assert 0.05 < float(dist("WRA", "WRB").median()) < 0.1  # the styloids, no bar


def test_synthetic_extra_markers_are_null_and_off_the_layout():
    """Markers of another protocol: 0..E per frame, on the body away from the layout, labelled null."""
    lay = MarkerLayout.load("pig39")
    cfg = SyntheticConfig(identities=4, extras=10, extra_prob=1.0, noise=(0.0, 0.0), spread=0.0, stick_prob=0.0)
    syn = SyntheticMocap(lay, cfg)
    rest_mean = syn.layer.identity(torch.zeros(1, 16))[0]
    pool = syn.used[syn.extra_pool]
    assert len(pool) == 2048
    assert torch.cdist(rest_mean[pool], rest_mean[lay.vertices]).min() >= cfg.extra_distance[0]
    markers, extra = syn.markers_and_extras(4000, torch.Generator().manual_seed(1), 10)
    assert markers.shape == (4000, 39, 3) and extra.shape == (4000, 10, 3)
    count = torch.isfinite(extra).all(-1).sum(1)
    assert count.min() == 0 and count.max() == 10 and abs(float(count.float().mean()) - 5.0) < 0.2
    # on the body: an extra marker is within 0.35 m of the frame's layout markers (bare thigh: 0.30 m)
    near = torch.cdist(extra.nan_to_num(0.0), markers).min(-1).values
    assert near[torch.isfinite(extra).all(-1)].max() < 0.35
    batch = syn.sample(64, torch.Generator().manual_seed(2))
    assert batch.points.shape[1] == 39 + cfg.ghosts[1] + 10
    null_real = (batch.labels == 39) & batch.mask
    assert null_real.sum(1).max() > cfg.ghosts[1]  # more null points than ghosts alone can give
    assert (batch.available.sum(1) == (batch.mask & (batch.labels < 39)).sum(1)).all()


def test_synthetic_extra_markers_in_tracking_clusters():
    """extra_clusters: each run of cluster_size extras is a plate of distinct vertices within
    cluster_radius of its first one on the rest mesh; without it, extras scatter over the body."""
    lay = MarkerLayout.load("pig39")
    cfg = SyntheticConfig(identities=4, extras=12, extra_prob=1.0, extra_clusters=1.0, noise=(0.0, 0.0), spread=0.0)
    syn = SyntheticMocap(lay, cfg)
    gen = torch.Generator().manual_seed(3)
    pick = torch.randint(len(syn.extra_pool), (500, 12), generator=gen)
    members = syn._clusters(pick, gen).reshape(500, 4, 3)
    mean = syn.layer.identity(torch.zeros(1, 16))[0][syn.used[syn.extra_pool]]
    centre = mean[pick[:, ::3]][:, :, None]
    assert float((mean[members] - centre).norm(dim=-1).max()) <= cfg.cluster_radius + 1e-6
    short = syn.cluster_count[pick[:, ::3]] >= 3
    distinct = (members.sort(-1).values.diff(dim=-1) != 0).all(-1)
    assert bool(distinct[short].all()) and short.float().mean() > 0.9
    _, grouped = syn.markers_and_extras(500, torch.Generator().manual_seed(4), 12, clusters=True)
    _, loose = syn.markers_and_extras(500, torch.Generator().manual_seed(4), 12)

    def spread(e):  # the largest distance within each full plate of 3, median over plates
        g = e.reshape(500, 4, 3, 3)
        d = (g[:, :, :, None] - g[:, :, None]).norm(dim=-1).flatten(2).amax(-1)
        return d[torch.isfinite(d)].median()

    assert spread(grouped) < 0.16 < 0.3 < spread(loose)


def test_sample_poses_legs_together():
    """together=1 adducts both hips 0-0.15 rad and flexes the right hip and knee as the left
    ones (+-0.15 rad, in range); together=0 leaves the stream as it was; the feet come closer."""
    g = torch.Generator
    a = sample_poses(512, g().manual_seed(4))
    b = sample_poses(512, g().manual_seed(4), together=1.0)
    (ll, rl), (ls, rs) = [[joint_index(s + x) - 1 for s in ("Left", "Right")] for x in ("Leg", "Shin")]
    assert torch.equal(a, sample_poses(512, g().manual_seed(4), together=0.0))
    assert torch.equal(a[:, ls], b[:, ls]) and torch.equal(a[:, ll, :2], b[:, ll, :2])  # left: abduction only
    assert (b[:, ll, 2] <= 1e-6).all() and (b[:, ll, 2] >= -0.15 - 1e-6).all()  # toward the midline
    assert (b[:, rl, 2] >= -1e-6).all() and (b[:, rl, 2] <= 0.15 + 1e-6).all()  # mirrored
    assert (b[:, rl, 0] - b[:, ll, 0]).abs().max() <= 0.15 + 1e-6
    assert (b[:, rs, 0] - b[:, ls, 0]).abs().max() <= 0.15 + 1e-6 and (b[:, rs, 0] >= 0).all()
    assert (a[:, rl, 0] - a[:, ll, 0]).abs().max() > 1.0  # independent legs differ widely
    with pytest.raises(ValueError, match="together"):
        sample_poses(2, g(), together=-0.1)


def test_sample_poses_arms_alike():
    """arms_alike=1 mirrors the left arm onto the right (+-0.15 rad); the left side is untouched."""
    g = torch.Generator
    a = sample_poses(256, g().manual_seed(5), together=0.5)
    b = sample_poses(256, g().manual_seed(5), together=0.5, arms_alike=1.0)
    for name in ("Shoulder", "Arm", "ForeArm", "Hand"):
        left, right = joint_index("Left" + name) - 1, joint_index("Right" + name) - 1
        assert torch.equal(a[:, left], b[:, left])
        mirrored = b[:, left] * torch.tensor([1.0, -1.0, -1.0])
        assert (b[:, right] - mirrored).abs().max() <= 0.15 + 1e-6 < (a[:, right] - mirrored).abs().max()
    with pytest.raises(ValueError, match="arms_alike"):
        sample_poses(2, g(), arms_alike=2.0)


def test_sample_poses_bend():
    """bend=1 flexes every elbow 1.2-2.4 rad (arm swing -1.5..1 rad) and every knee 1.2-2.3 rad
    with the hip flexed 0..knee; bend=0 leaves the stream as it was; a fraction bends that share."""
    g = torch.Generator
    a = sample_poses(512, g().manual_seed(6), together=0.3)
    assert torch.equal(a, sample_poses(512, g().manual_seed(6), together=0.3, bend=0.0))
    b = sample_poses(512, g().manual_seed(6), bend=1.0)
    for side, sign in (("Left", -1.0), ("Right", 1.0)):
        elbow = sign * b[:, joint_index(side + "ForeArm") - 1, 1]
        swing = -sign * b[:, joint_index(side + "Arm") - 1, 1]
        knee, hip = b[:, joint_index(side + "Shin") - 1, 0], b[:, joint_index(side + "Leg") - 1, 0]
        assert elbow.min() >= 1.2 and elbow.max() <= 2.4 and elbow.max() - elbow.min() > 1.1
        assert swing.min() >= -1.5 and swing.max() <= 1.0 and swing.max() - swing.min() > 2.3
        assert knee.min() >= 1.2 and knee.max() <= 2.3
        assert (hip <= 0).all() and (hip >= torch.maximum(-knee, torch.tensor(-2.0)) - 1e-6).all()
    c = sample_poses(4096, g().manual_seed(7), bend=0.3)
    knee = c[:, joint_index("LeftShin") - 1, 0]
    base = sample_poses(4096, g().manual_seed(7))[:, joint_index("LeftShin") - 1, 0]
    assert 0.25 < float((knee >= 1.2).float().mean()) - 0.7 * float((base >= 1.2).float().mean()) < 0.35
    with pytest.raises(ValueError, match="bend"):
        sample_poses(2, g(), bend=1.5)


def test_sample_poses_chamber_brings_the_fist_to_the_waist():
    """chamber=1 holds every fist beside the waist (FIN within 25 cm of the same side's FWT in
    four samples in five; the default recipe without it: under one in five), elbows flexed
    1.4-2.3 rad; chamber=0 leaves the stream as it was."""
    g = torch.Generator
    a = sample_poses(256, g().manual_seed(8), bend=0.3, arms_alike=0.4)
    assert torch.equal(a, sample_poses(256, g().manual_seed(8), bend=0.3, arms_alike=0.4, chamber=0.0))
    b = sample_poses(256, g().manual_seed(8), chamber=1.0)
    for side, sign in (("Left", -1.0), ("Right", 1.0)):
        elbow = sign * b[:, joint_index(side + "ForeArm") - 1, 1]
        assert elbow.min() >= 1.4 and elbow.max() <= 2.3
    lay = MarkerLayout.load("cmu41")
    near = {}
    for c in (0.0, 1.0):
        cfg = SyntheticConfig(identities=8, noise=(0.0, 0.0), pose=dict(POSE, chamber=c))
        m = SyntheticMocap(lay, cfg).markers(1000, g().manual_seed(0))
        d = torch.cat([(m[:, lay.index(s + "FIN")] - m[:, lay.index(s + "FWT")]).norm(dim=-1) for s in "LR"])
        near[c] = float((d < 0.25).float().mean())
    assert near[0.0] < 0.2 and near[1.0] > 0.75, near
    with pytest.raises(ValueError, match="chamber"):
        sample_poses(2, g(), chamber=-0.1)


def test_sample_poses_fold_closes_the_hips():
    """fold=1 flexes both hips 1.2-2.0 rad (the right within 0.2 of the left), each knee 0-2.3 rad
    and the spine forward within its range, so the trunk-thigh marker angle (SHO-FWT-KNE) is
    under 105 deg in most samples (the default recipe: one in twenty); fold=0 leaves the stream
    as it was; other joints keep their draws."""
    g = torch.Generator
    a = sample_poses(256, g().manual_seed(9), bend=0.3, arms_alike=0.4, chamber=0.2)
    assert torch.equal(a, sample_poses(256, g().manual_seed(9), bend=0.3, arms_alike=0.4, chamber=0.2, fold=0.0))
    b = sample_poses(256, g().manual_seed(9), bend=0.3, arms_alike=0.4, chamber=0.2, fold=1.0)
    hip = {s: b[:, joint_index(s + "Leg") - 1, 0] for s in ("Left", "Right")}
    assert hip["Left"].max() <= -1.2 and hip["Left"].min() >= -2.0 - 1e-6
    assert (hip["Right"] - hip["Left"]).abs().max() <= 0.2 + 1e-6 and hip["Right"].min() >= -2.0
    for side in ("Left", "Right"):
        knee = b[:, joint_index(side + "Shin") - 1, 0]
        assert knee.min() >= 0 and knee.max() <= 2.3 and knee.max() - knee.min() > 2.0
    for name, top in (("Spine1", 0.35), ("Spine2", 0.35), ("Chest", 0.25)):
        flex = b[:, joint_index(name) - 1, 0]
        assert flex.min() >= 0 and flex.max() <= top
    head = joint_index("Head") - 1
    assert torch.equal(a[:, head], b[:, head])
    lay = MarkerLayout.load("cmu41")
    closed = {}
    for f in (0.0, 1.0):
        cfg = SyntheticConfig(identities=8, noise=(0.0, 0.0), pose=dict(POSE, fold=f))
        m = SyntheticMocap(lay, cfg).markers(1000, g().manual_seed(0))
        u, v = (m[:, lay.index(x)] - m[:, lay.index("LFWT")] for x in ("LSHO", "LKNE"))
        angle = torch.rad2deg(torch.acos(torch.nn.functional.cosine_similarity(u, v, dim=-1).clamp(-1, 1)))
        closed[f] = float((angle < 105).float().mean())
    assert closed[0.0] < 0.1 and closed[1.0] > 0.6, closed
    with pytest.raises(ValueError, match="fold"):
        sample_poses(2, g(), fold=1.5)


def test_sample_poses_range_overrides():
    """A ranges entry replaces that joint's range; other joints keep theirs; unknown joints fail."""
    wide = {"Head": ((-0.2, -1.0, -0.15), (0.3, 1.0, 0.15), (0.0, 0.0, 0.0))}
    a = sample_poses(2000, torch.Generator().manual_seed(3))
    b = sample_poses(2000, torch.Generator().manual_seed(3), ranges=wide)
    head = joint_index("Head") - 1
    assert a[:, head, 1].abs().max() <= 0.3 + 1e-6 < b[:, head, 1].abs().max() <= 1.0 + 1e-6
    knee = joint_index("LeftShin") - 1
    assert torch.equal(a[:, knee], b[:, knee])  # same stream, same draws elsewhere
    with pytest.raises(ValueError, match="ranges"):
        sample_poses(2, torch.Generator(), ranges={"Tail": wide["Head"]})


@pytest.mark.parametrize(
    ("name", "bands", "pairs"),
    [
        ("cmu41", (), (("BHD", "FHD"), ("BWT", "FWT"))),
        ("pig39", (("FHD", 0.0, 80.0), ("BHD", 100.0, 180.0)), (("BHD", "FHD"), ("PSI", "ASI"))),
    ],
)
def test_synthetic_pairs_stay_on_their_side(name, bands, pairs):
    """A left marker is drawn on the left: on the mean rest mesh every candidate of a pair's marker is
    on its own side, side_margin or more from the sagittal plane; in posed samples the back pair of
    the head (the waist) is ordered as the front pair, but where deep neck turns bend the skin. Without
    the rule the back-head (cmu41) and PSIS (pig39) markers cross in 7 and 4 % of the samples."""
    lay = MarkerLayout.load(name)
    cfg = SyntheticConfig(identities=16, bands=bands, noise=(0.0, 0.0), stick_prob=0.0)

    def crossed(syn: SyntheticMocap) -> dict[str, float]:
        m = syn.markers(3000, torch.Generator().manual_seed(0))
        out = {}
        for back, front in pairs:
            axis = m[:, lay.index("L" + front)] - m[:, lay.index("R" + front)]
            across = ((m[:, lay.index("L" + back)] - m[:, lay.index("R" + back)]) * axis).sum(-1)
            out[back] = float((across <= 0).float().mean())
        return out

    syn = SyntheticMocap(lay, cfg)
    assert max(crossed(syn).values()) < 0.002, crossed(syn)
    assert max(crossed(SyntheticMocap(lay, replace(cfg, side_margin=-1.0))).values()) > 0.03  # the rule off
    rest = syn.layer.prepare_identity(torch.zeros(1, 16)).rest_vertices[0]
    for label in lay.labels:
        if label[0] in "LR" and ("R" if label[0] == "L" else "L") + label[1:] in lay.labels:
            i = lay.index(label)
            x = rest[syn.used[syn.candidates[i, : syn.num_candidates[i]]], 0]
            sign = 1.0 if label[0] == "L" else -1.0
            assert float((sign * x).min()) >= syn.config.side_margin - 1e-6, label


def test_synthetic_take_keeps_one_actor_and_placement():
    """A take: one body and one placement for all its frames (a still pose gives the same markers in
    every frame; the head's markers keep their distances while the body moves), its path turned with
    its heading (the vertical unchanged, the horizontal lengths kept), seeded, and shapes checked."""
    lay = MarkerLayout.load("cmu41")
    syn = SyntheticMocap(lay, SyntheticConfig(identities=16, noise=(0.0, 0.0)))
    g = torch.Generator().manual_seed(3)
    pose = sample_poses(1, g).expand(5, -1, -1)
    still = syn.take(pose, torch.Generator().manual_seed(1))
    assert still.shape == (5, 41, 3) and bool(torch.isfinite(still).all())
    assert float((still - still[:1]).abs().max()) < 1e-5
    moving = sample_poses(40, g)
    a = syn.take(moving, torch.Generator().manual_seed(2))
    assert torch.equal(a, syn.take(moving, torch.Generator().manual_seed(2)))
    hd = [lay.index(x) for x in ("LFHD", "RFHD", "LBHD", "RBHD")]
    dist = torch.cdist(a[:, hd], a[:, hd])  # (T, 4, 4)
    assert float(dist.std(0).max()) < 2e-3  # rigid head (the neck's weights reach the back markers a little)
    # the path: the same take with and without it differs by the path turned about the vertical
    path = torch.cumsum(0.01 * torch.randn(40, 3, generator=g), 0)
    b = syn.take(moving, torch.Generator().manual_seed(2), path)
    shift = b - a  # (T, M, 3): every marker moved by the turned path
    assert float((shift - shift[:, :1]).abs().max()) < 1e-5
    s = shift[:, 0]
    assert torch.allclose(s[:, 1], path[:, 1], atol=1e-5)
    assert torch.allclose(s[:, [0, 2]].norm(dim=-1), path[:, [0, 2]].norm(dim=-1), atol=1e-5)
    with pytest.raises(ValueError, match="pose"):
        syn.take(moving[:, :10], g)
    with pytest.raises(ValueError, match="transl"):
        syn.take(moving, g, path[:5])
    with pytest.raises(ValueError, match="pose"):
        syn.take(torch.full_like(moving, float("nan")), g)
    with pytest.raises(ValueError, match="transl"):
        syn.take(moving, g, torch.full_like(path, float("inf")))
