"""Mocap labeling and body solve on real, labelled C3D files (paper 003 protocol; evaluation only).

    OMP_NUM_THREADS=2 python benchmarks/mocap.py [--evaldata ../shared/evaldata]
        [--sections label body speed solve copies retry] [--files KEY ...] [--retry R] [--bf16]
        [--speed-also cmu41_large]
        [--session pycgm=build/s2_pycgm/labeler.pt tennis=build/s2_tennis/labeler.pt]

Labels are hidden from the labeler and used only to score it. Files: CMU 85_02, 85_12, 135_02
(CMU 41 layout, ``cmu41`` model); BTKData Plug-in Gait walking / static (35 markers), pyCGM
static + stair descent and the tennis serve (39 markers; ``pig39`` model). Unlabelled ``*``
points in a file are real ghosts (truth: null).

- **per-frame**: every frame independently, with synthetic corruption drawn per frame
  (paper Table 1 "B+C+G"): 0-5 occluded markers, 0-3 ghost points, random permutation.
  Also a no-noise row (permutation only) and exact occlusion counts 0..5 and 5 + 3 ghosts
  (paper Table 2).
- **tracklet**: the sequence keeps its columns; the same per-frame occlusions and ghosts
  (ghosts in extra columns), 50 broken trajectories (paper §4.4), per-frame labels, then the
  majority label per column ("vote", ``label_tracklets``) and the settled spans ("tracklet",
  ``settle_tracklets``, what ``unibody mocap label`` does). **joined**: the same sequence with
  10 more errors of a tracker, two trajectories joined wrongly (two columns swap their samples
  from a random frame on): a column's evidence is split over time.
- **session layouts** (``--session KEY=WEIGHTS ...``, paper §4.5): the files whose name holds
  KEY are labelled again by a labeler of their session's layout (``unibody mocap layout`` on
  one frame: the model's markers at the session's places and its other markers, named X01...);
  its extra labels count as null, so its rows score the same labels as the model's, and one
  pooled row takes every session's files from its own labeler.
- Scores: accuracy over all real points and macro F1 over the labels present incl. null.
- **body** (``unibody.mocap.relabel``): the per-frame C+G labels and the tracklet labels of
  the rows above (the same draws), checked against a body solved from them: per frame
  (``relabel``: each point takes the solved marker it sits on, where that is clear; four solves)
  and on tracklets (``relabel_tracklets``: the body's labels are more evidence for the spans;
  one solve at >= 50 Hz). It uses the whole sequence (the solve's shape and temporal prior), so
  it is a sequence labelling, not a per-frame one. Frames/s: each check of a file.
- **speed**: labeling frames/s at batch 1 and 256 (forward + decoding) on 256 real frames
  spread over each model's files, corrupted as per-frame C+G, with the two-stage labelers'
  retry confidence (their cost depends on the frames) and without retries; best and median
  of 5 rounds.
- ``--retry R`` sets the two-stage labelers' retry confidence (0: no retries); ``--bf16`` runs
  the labelers' networks in bfloat16 (``Labeler.set_autocast``; fast on CPUs with AMX).
- **copies** (not in the default sections): ``label_sequence`` on each whole file and on the file
  with three more columns that copy three markers exactly; a copy is right when it has its
  original's label (``unibody.mocap.coincident``).
- **retry** (not in the default sections): ``label_sequence`` on each whole file with every
  unsure frame retried (the path before) and with only the frames that could change a settled
  span retried (``sequence_probabilities``): accuracy, frames retried, CPU s, labels that differ.
- **solve**: the body solve on the files' own labels: mean / median marker residual,
  fraction of frames solved, frames/s of the whole solve; a PNG of one solved frame.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from unibody.mocap.c3d import MarkerSequence, read_markers
from unibody.mocap.corrupt import MocapBatch, break_trajectories, corrupt_frames
from unibody.mocap.labeler import Labeler, frame_probabilities, predict, sequence_probabilities
from unibody.mocap.layout import MarkerLayout
from unibody.mocap.metrics import labeling_scores
from unibody.mocap.pipeline import label_sequence, load_labeler, render_solution, solve_sequence
from unibody.mocap.relabel import relabel, relabel_tracklets
from unibody.mocap.solve import SolveConfig, lab_to_unibody
from unibody.mocap.tracklets import label_tracklets, settle_tracklets

FILES = {
    "cmu41": ["c3d/cmu_85_02.c3d", "c3d/cmu_85_12.c3d", "c3d/cmu_135_02.c3d"],
    "pig39": [
        "c3d/btkdata_PiG_Motion-FlatFoot-Full.c3d",
        "c3d/btkdata_PiG_Motion-FlatFoot-One.c3d",
        "c3d/btkdata_PiG_Calibration-FlatFoot-Full.c3d",
        "c3d/btkdata_PiG_Calibration-FlatFoot-Hole.c3d",
        "c3d/pycgm_Static_trial.c3d",
        "c3d/pycgm_Movement_trial.c3d",
        "c3d/ktk_kinematics_tennis_serve.c3d",
    ],
}


MAX_FRAMES: int | None = None


def read(path: Path) -> MarkerSequence:
    seq = read_markers(path)
    if MAX_FRAMES is None:
        return seq
    return MarkerSequence(seq.points[:MAX_FRAMES], seq.labels, seq.subjects, seq.rate)


def split(seq: MarkerSequence, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(T, L, 3) the model's labels (NaN if absent), Y up; (T, G, 3) the file's other points."""
    pts = lab_to_unibody(seq.points, up="z")
    idx = {x: i for i, x in enumerate(seq.labels)}
    marked = np.stack([pts[:, idx[x]] if x in idx else np.full(pts[:, 0].shape, np.nan) for x in names], axis=1)
    others = [i for i, x in enumerate(seq.labels) if x not in set(names)]
    return marked, pts[:, others]


def with_real_ghosts(batch: MocapBatch, ghosts: torch.Tensor, null: int) -> MocapBatch:
    """Append the file's unlabelled points (T, G, 3, NaN = absent) as null points."""
    ok = torch.isfinite(ghosts).all(-1)
    pts = torch.cat([batch.points, torch.where(ok[..., None], ghosts, 0.0)], dim=1)
    labels = torch.cat([batch.labels, torch.full(ok.shape, null, dtype=torch.long)], dim=1)
    return MocapBatch(pts, torch.cat([batch.mask, ok], dim=1), labels, batch.available)


def corrupted(marked, real_ghosts, gen, null: int, **corruption):
    """(start frame, MocapBatch) of a file's frames corrupted per frame, 512 frames at a time."""
    m = torch.as_tensor(marked, dtype=torch.float32)
    g = torch.as_tensor(real_ghosts, dtype=torch.float32)
    for s in range(0, len(m), 512):
        yield s, with_real_ghosts(corrupt_frames(m[s : s + 512], gen, **corruption), g[s : s + 512], null)


def per_frame(model: Labeler, marked, real_ghosts, gen, frames: list | None = None, **corruption):
    """Predicted and true labels of every real point; ``frames`` (a list) receives each point's frame."""
    preds, truths = [], []
    with torch.no_grad():
        for s, b in corrupted(marked, real_ghosts, gen, model.num_labels, **corruption):
            pred, _ = predict(model(b.points, b.mask), b.mask)
            preds.append(pred[b.mask])
            truths.append(b.labels[b.mask])
            if frames is not None:
                frames.append(b.mask.nonzero()[:, 0] + s)
    return torch.cat(preds), torch.cat(truths)


UPRIGHT_BINS = ((0.9, "upright"), (0.5, "leaning"), (-0.5, "lying"), (-1.01, "inverted"))


def trunk_up(marked: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """(T,) cosine between the vertical and the pelvis-to-C7 direction (NaN where unseen)."""
    pelvis = [names.index(x) for x in names if x[1:] in ("ASI", "PSI", "FWT", "BWT")]
    up = marked[:, names.index("C7")] - np.nanmean(marked[:, pelvis], axis=1)
    return up[:, 1] / np.linalg.norm(up, axis=1)


def posture_bin(cos: np.ndarray) -> np.ndarray:
    """Index into UPRIGHT_BINS of each cosine (NaN -> -1)."""
    out = np.full(cos.shape, -1)
    for k in reversed(range(len(UPRIGHT_BINS))):
        out[cos >= UPRIGHT_BINS[k][0]] = k
    return out


def broken_sequence(marked, ghosts, rng, null: int) -> tuple[np.ndarray, np.ndarray]:
    """Columns kept: occlusions / ghosts per frame, 50 broken trajectories; (T, N, 3) points, (N,) true labels."""
    t, nl, _ = marked.shape
    seq = np.concatenate([marked, ghosts, np.full((t, 3, 3), np.nan)], axis=1)
    truth_col = np.concatenate([np.arange(nl), np.full(seq.shape[1] - nl, null)])
    vis = np.isfinite(seq).all(-1)
    # occlusions: 0..5 of the visible labelled markers per frame
    for f in range(t):
        cand = np.nonzero(vis[f, :nl])[0]
        k = min(int(rng.integers(0, 6)), len(cand))
        seq[f, rng.choice(cand, k, replace=False)] = np.nan
        # ghosts: 0..3 from N(median, std) of the visible markers, in the 3 spare columns
        visible = seq[f, :nl][np.isfinite(seq[f, :nl]).all(-1)]
        for j in range(int(rng.integers(0, 4))):
            seq[f, -3 + j] = np.median(visible, 0) + visible.std(0) * rng.standard_normal(3)
    broken, source = break_trajectories(seq, 50, rng)
    return broken, truth_col[source]


def join_trajectories(points, truth, count: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """Two trajectories joined wrongly, ``count`` times: at a frame t in [2, T-1), two columns visible
    at t with different true labels swap their samples from t on (a tracker that swapped two markers
    that came close); (T, N, 3) points and (T, N) per-sample true labels."""
    pts, tru = points.copy(), np.array(truth, copy=True)
    t = len(pts)
    for _ in range(count):
        for _ in range(100):
            f = int(rng.integers(2, t - 1))
            cols = np.flatnonzero(np.isfinite(pts[f]).all(-1))
            if len(cols) < 2:
                continue
            i, j = rng.choice(cols, 2, replace=False)
            if tru[f, i] != tru[f, j]:
                pts[f:, [i, j]] = pts[f:, [j, i]]
                tru[f:, [i, j]] = tru[f:, [j, i]]
                break
    return pts, tru


JOINS = 10  # wrongly joined trajectory pairs per file (the "joined" protocol)


def tracklet(model: Labeler, marked, ghosts, gen: torch.Generator, rng) -> dict[str, tuple]:
    """Broken sequence (:func:`broken_sequence`), per-frame labels, then the sequence's labels:
    the majority vote per column (``vote``) and :func:`settle_tracklets` (``tracklet``, on
    ``sequence_probabilities`` as ``label_sequence`` does: retries only where they can matter); then the
    same sequence with :data:`JOINS` wrongly joined trajectory pairs (``joined_*``)."""
    null = model.num_labels
    broken, truth = broken_sequence(marked, ghosts, rng, null)
    rows = {}
    joined, jtruth = join_trajectories(broken, np.broadcast_to(truth, broken.shape[:2]), JOINS, rng)
    for key, pts, tru in (("", broken, np.broadcast_to(truth, broken.shape[:2])), ("joined_", joined, jtruth)):
        vis = torch.from_numpy(np.isfinite(pts).all(-1))
        fl = frame_probabilities(model, torch.as_tensor(pts, dtype=torch.float32))
        tru = torch.from_numpy(np.ascontiguousarray(tru))
        rows[f"{key}frame"] = (fl.labels[vis], tru[vis])
        rows[f"{key}vote"] = (label_tracklets(fl.labels, vis, null)[vis], tru[vis])
        # settled as label_sequence does: from sequence_probabilities (retries only where they can matter)
        seq_prob = sequence_probabilities(model, torch.as_tensor(pts, dtype=torch.float32)).prob
        rows[f"{key}tracklet"] = (settle_tracklets(seq_prob, vis)[vis], tru[vis])
    return rows


def fmt(scores: dict) -> str:
    return f"{100 * scores['accuracy']:6.2f} {100 * scores['f1']:6.2f}"


def score_file(model: Labeler, seq: MarkerSequence, seed: int, base: int, frames: list | None = None) -> dict:
    """Predicted and true labels of the no-noise, per-frame C+G, tracklet rows of one file.

    Labels ``base`` and above (a session model's extra markers, null) are scored as null (``base``).
    """
    marked, ghosts = split(seq, model.label_names)
    gen = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)
    clean = per_frame(model, marked, ghosts, gen, occlusions=(0, 0), ghosts=(0, 0))
    noisy = per_frame(model, marked, ghosts, gen, frames)
    tr = tracklet(model, marked, ghosts, gen, rng)
    rows = {"clean": clean, "noisy": noisy, "tr_frame": tr["frame"], "vote": tr["vote"], "tracklet": tr["tracklet"]}
    rows.update({f"j_{k}": tr[f"joined_{k}"] for k in ("frame", "vote", "tracklet")})
    return {k: (p.clamp_max(base), t.clamp_max(base)) for k, (p, t) in rows.items()}


ROW_KEYS = ("clean", "noisy", "tr_frame", "vote", "tracklet", "j_frame", "j_vote", "j_tracklet")
HEADER = (
    "| file | model | frames | no noise | per-frame C+G | tracklet: per-frame | tracklet: vote | tracklet "
    "| joined: per-frame | joined: vote | joined: tracklet |\n|---|---|---|---|---|---|---|---|---|---|---|"
)


def row(name: str, model: str, frames, scores: dict) -> str:
    return f"| {name} | {model} | {frames} | " + " | ".join(fmt(scores[k]) for k in ROW_KEYS) + " |"


def pool(files: list[dict], null: int) -> dict:
    return {k: labeling_scores(*map(torch.cat, zip(*(f[k] for f in files), strict=True)), null=null) for k in files[0]}


def session_rows(root: Path, models: dict[str, Labeler], sessions: dict[str, Labeler], per_file: dict, seed: int):
    """The files of each session labelled by its session model, and the pooled rows with them."""
    print("\n## Session layouts (paper §4.5): the same rows, the session's files by its own labeler")
    print(HEADER)
    for name, files in FILES.items():
        base = models[name]
        mine = {k: m for k, m in sessions.items() if m.label_names[: base.num_labels] == base.label_names}
        pooled, used = [], []
        for rel in files:
            key = next((k for k in mine if k in Path(rel).stem), None)
            if key is None:
                pooled.append(per_file[rel])
                continue
            seq, smodel = read(root / rel), mine[key]
            rows = score_file(smodel, seq, seed, base.num_labels)
            pooled.append(rows)
            used.append(key)
            scores = {k: labeling_scores(*v, null=base.num_labels) for k, v in rows.items()}
            print(row(Path(rel).stem, f"{key} ({smodel.num_labels})", seq.num_frames, scores), flush=True)
        if used:
            keys = ", ".join(dict.fromkeys(used))
            print(row(f"**all {name} files, {keys} by their session models**", name, "", pool(pooled, base.num_labels)))


def label_section(root: Path, models: dict[str, Labeler], seed: int, sessions: dict[str, Labeler]) -> None:
    print("\n## Labeling (accuracy / macro F1, %; labels hidden)")
    print(HEADER)
    table2: dict[str, list] = {}
    postures: dict[str, list] = {}
    per_file: dict[str, dict] = {}
    for name, files in FILES.items():
        model = models[name]
        for rel in files:
            seq = read(root / rel)
            marked, ghosts = split(seq, model.label_names)
            frames: list = []
            rows = per_file[rel] = score_file(model, seq, seed, model.num_labels, frames)
            noisy = rows["noisy"]
            gen = torch.Generator().manual_seed(seed + 1)
            bins = torch.from_numpy(posture_bin(trunk_up(marked, model.label_names)))[torch.cat(frames)]
            for k in range(len(UPRIGHT_BINS)):
                postures.setdefault(name, [[] for _ in UPRIGHT_BINS])[k].append(
                    (noisy[0][bins == k], noisy[1][bins == k])
                )
            s = {k: labeling_scores(*v, null=model.num_labels) for k, v in rows.items()}
            print(row(Path(rel).stem, name, len(marked), s), flush=True)
            for k in range(6):
                table2.setdefault(name, [[] for _ in range(7)])
                table2[name][k].append(
                    per_frame(model, marked, ghosts, gen, occlusions=(k, k), ghosts=(0, 0), exact=True)
                )
            table2[name][6].append(per_frame(model, marked, ghosts, gen, occlusions=(5, 5), ghosts=(3, 3), exact=True))
    for name, files in FILES.items():
        print(row(f"**all {name} files**", name, "", pool([per_file[rel] for rel in files], models[name].num_labels)))
    if sessions:
        session_rows(root, models, sessions, per_file, seed)
    print("\n## Per-frame accuracy / F1 (%) by exact number of occlusions (paper Table 2), pooled files")
    print("| model | 0 | 1 | 2 | 3 | 4 | 5 | 5+G |\n|---|---|---|---|---|---|---|---|")
    for name, cols in table2.items():
        cells = [
            fmt(labeling_scores(*map(torch.cat, zip(*c, strict=True)), null=models[name].num_labels)) for c in cols
        ]
        print(f"| {name} | " + " | ".join(cells) + " |")
    print("\n## Per-frame C+G accuracy / F1 (%) by posture (cosine of the pelvis-to-C7 axis with the vertical)")
    heads = " | ".join(f"{label} (>= {lo:g})" if lo > -1 else label for lo, label in UPRIGHT_BINS)
    print(f"| model | {heads} |\n|---|" + "---|" * len(UPRIGHT_BINS))
    for name, cols in postures.items():
        cells = []
        for c in cols:
            pred, truth = map(torch.cat, zip(*c, strict=True))
            share = f"{100 * len(truth) / sum(len(t) for x in cols for _, t in x):.0f} % of points"
            cells.append(
                f"{fmt(labeling_scores(pred, truth, null=models[name].num_labels))} ({share})" if len(truth) else "-"
            )
        print(f"| {name} | " + " | ".join(cells) + " |")


def body_section(root: Path, models: dict[str, Labeler], seed: int) -> None:
    """The label section's per-frame C+G and tracklet labels (the same draws), then checked by a body solve."""
    print("\n## Body-checked labels (unibody.mocap.relabel: a body solved from the labels, points re-assigned)")
    print(
        "| file | model | frames | per-frame C+G | + body | tracklet | tracklet + body "
        "| body check, frames/s (per-frame / tracklet) |\n"
        "|---|---|---|---|---|---|---|---|"
    )
    for name, files in FILES.items():
        model, layout, null = models[name], MarkerLayout.load(name), models[name].num_labels
        pooled = []
        for rel in files:
            seq = read(root / rel)
            marked, ghosts = split(seq, model.label_names)
            gen = torch.Generator().manual_seed(seed)
            for _ in corrupted(marked, ghosts, gen, null, occlusions=(0, 0), ghosts=(0, 0)):
                pass  # the label section's no-noise draw comes first
            batches = [b for _, b in corrupted(marked, ghosts, gen, null)]
            mask = torch.cat([b.mask for b in batches])
            truth = torch.cat([b.labels for b in batches])
            pts = torch.where(mask[..., None], torch.cat([b.points for b in batches]).double(), np.nan)
            with torch.no_grad():
                pred = torch.cat([predict(model(b.points, b.mask), b.mask)[0] for b in batches])
            broken, col_truth = broken_sequence(marked, ghosts, np.random.default_rng(seed), null)
            broken_t = torch.as_tensor(broken)
            vis = torch.isfinite(broken_t).all(-1)
            prob = sequence_probabilities(model, broken_t.float()).prob
            track = settle_tracklets(prob, vis)
            t = time.perf_counter()
            checked, _ = relabel(pts, pred, layout, fps=seq.rate)
            t1 = time.perf_counter()
            track_checked, _ = relabel_tracklets(broken_t, prob, layout, fps=seq.rate)
            rates = f"{len(marked) / (t1 - t):.0f} / {len(marked) / (time.perf_counter() - t1):.0f}"
            col_truth = torch.from_numpy(col_truth).expand(vis.shape)
            rows = {
                "frame": (pred[mask], truth[mask]),
                "body": (checked[mask], truth[mask]),
                "tracklet": (track[vis], col_truth[vis]),
                "tracklet_body": (track_checked[vis], col_truth[vis]),
            }
            pooled.append(rows)
            cells = " | ".join(fmt(labeling_scores(*v, null=null)) for v in rows.values())
            print(f"| {Path(rel).stem} | {name} | {len(marked)} | {cells} | {rates} |", flush=True)
        cells = " | ".join(fmt(v) for v in pool(pooled, null).values())
        print(f"| **all {name} files** | {name} | | {cells} | |", flush=True)


COPIED = {"cmu41": ("LFWT", "CLAV", "LFHD"), "pig39": ("LASI", "CLAV", "LFHD")}


def copies_section(root: Path, models: dict[str, Labeler]) -> None:
    """``label_sequence`` (settled tracklets) on each file as it is and with three more columns that
    copy three of its markers exactly (as a held-out lab's exports do): accuracy / F1 of every
    point (a copy is right when it has its original's label), the copy columns found, CPU s."""
    print("\n## Copied columns (label_sequence on the whole file; a copy is right with its original's label)")
    print("| file | model | frames | as it is | with 3 copied columns | copy columns found | CPU s (as is / copies) |")
    print("|---|---|---|---|---|---|---|")
    for name, files in FILES.items():
        model, null = models[name], models[name].num_labels
        for rel in files:
            seq = read(root / rel)
            own = [seq.labels.index(x) for x in COPIED[name] if x in seq.labels]
            pts = np.concatenate([seq.points, seq.points[:, own]], axis=1)
            names = (*seq.labels, *(f"COPY{i}" for i in range(len(own))))
            copied = MarkerSequence(pts, names, ("",) * len(names), seq.rate)
            truth = np.array([model.label_names.index(x) if x in model.label_names else null for x in seq.labels])
            truth = np.concatenate([truth, truth[own]])
            cells, times, found = [], [], ""
            for s in (seq, copied):
                t = time.process_time()
                out = label_sequence(s, model)
                times.append(time.process_time() - t)
                vis = torch.from_numpy(s.visible)
                tru = torch.from_numpy(np.broadcast_to(truth[: s.num_markers], vis.shape).copy())
                cells.append(fmt(labeling_scores(torch.from_numpy(out.point_labels)[vis], tru[vis], null=null)))
                found = ", ".join(f"{c}={o}" for c, o in out.report.copies)
            print(f"| {Path(rel).stem} | {name} | {seq.num_frames} | {cells[0]} | {cells[1]} | {found} | "
                  f"{times[0]:.1f} / {times[1]:.1f} |", flush=True)  # fmt: skip


def retry_section(root: Path, models: dict[str, Labeler]) -> None:
    """``label_sequence`` on each whole file (its own points, no added noise) two ways: every
    unsure frame retried (``frame_probabilities``, the path before) and only the unsure frames
    that could change a settled span (``sequence_probabilities``, what it does now); accuracy /
    F1 of every point, frames retried, CPU s, and the points whose settled label differs."""
    from unittest import mock

    import unibody.mocap.pipeline as pipeline
    from unibody.mocap.tracklets import undecided_frames

    print("\n## Retries on whole files (label_sequence: every unsure frame vs the undecided ones only)")
    print("| file | model | frames | unsure frames | retried now | accuracy / F1: all retried | now "
          "| points labelled differently | CPU s: all retried / now |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for name, files in FILES.items():
        model, null = models[name], models[name].num_labels
        for rel in files:
            seq = read(root / rel)
            truth = np.array([model.label_names.index(x) if x in model.label_names else null for x in seq.labels])
            vis = torch.from_numpy(seq.visible)
            tru = torch.from_numpy(np.broadcast_to(truth, vis.shape).copy())
            counts = {}

            def counted(prob, visible, unsure, config=None, _c=counts):
                out = undecided_frames(prob, visible, unsure, config)
                _c["unsure"], _c["redo"] = int(unsure.sum()), int(out.sum())
                return out

            outs, cells, times = [], [], []
            for every in (True, False):
                t = time.process_time()
                if every:
                    with mock.patch.object(pipeline, "sequence_probabilities", frame_probabilities):
                        out = label_sequence(seq, model)
                else:
                    with mock.patch("unibody.mocap.tracklets.undecided_frames", counted):
                        out = label_sequence(seq, model)
                times.append(time.process_time() - t)
                outs.append(torch.from_numpy(out.point_labels))
                cells.append(fmt(labeling_scores(outs[-1][vis], tru[vis], null=null)))
            differ = int((outs[0] != outs[1])[vis].sum())
            unsure, redo = counts.get("unsure", 0), counts.get("redo", 0)
            print(f"| {Path(rel).stem} | {name} | {seq.num_frames} | {unsure} | {redo} | {cells[0]} | {cells[1]} "
                  f"| {differ} of {int(vis.sum())} | {times[0]:.1f} / {times[1]:.1f} |", flush=True)  # fmt: skip


def _gemm_rate(rounds: int) -> str:
    """float32 GFLOP/s of the labeler's widest product (a 256-frame pass's q/k/v projection), best / median."""
    x, w, bias = torch.randn(256 * 44, 96), torch.randn(96, 288), torch.randn(288)
    torch.addmm(bias, x, w)  # warm-up
    rates = []
    for _ in range(rounds):
        t = time.perf_counter()
        for _ in range(20):
            torch.addmm(bias, x, w)
        rates.append(20 * 2 * x.shape[0] * 96 * 288 / (time.perf_counter() - t) / 1e9)
    return f"addmm (11264, 96) @ (96, 288) at {max(rates):.0f} / {float(np.median(rates)):.0f} GFLOP/s, best / median"


def speed_section(root: Path, models: dict[str, Labeler], seed: int, rounds: int = 5, also=()) -> None:
    """Frames/s on 256 frames spread over each model's files, corrupted as per-frame C+G.

    Two-stage labelers run with their retry confidence and without retries (0). Each round
    labels all 256 frames; the best and the median round are printed (this VM's speed moves
    by tens of percent between runs: the best round is the least disturbed one). ``also``:
    (name, labeler) pairs timed beside the shipped model of their layout, rounds interleaved,
    with their speed as a ratio to it.
    """
    print(f"\n## Labeling speed (CPU, {torch.get_num_threads()} threads; forward + decoding, real frames)")
    print(f"Machine reference (this VM's speed moves between runs): {_gemm_rate(rounds)}.\n")
    print(f"| model | parameters | retry | batch | frames/s, best / median of {rounds} rounds | ratio to the first |")
    print("|---|---|---|---|---|---|")
    gen = torch.Generator().manual_seed(seed)
    for name, model in models.items():
        group = [(name, model)] + [(n, m) for n, m in also if m.label_names == model.label_names]
        marked = np.concatenate([split(read(root / rel), model.label_names)[0] for rel in FILES[name]])
        pick = np.linspace(0, len(marked) - 1, 256).round().astype(int)
        b = corrupt_frames(torch.as_tensor(marked[pick], dtype=torch.float32), gen)
        for retry in dict.fromkeys((model.config.retry, 0.0)):
            for size in (1, 256):
                batches = [(b.points[k : k + size], b.mask[k : k + size]) for k in range(0, 256, size)]
                times = {n: [] for n, _ in group}
                with torch.no_grad():
                    for _, m in group:
                        predict(m(*batches[0], retry=retry), batches[0][1])  # warm-up
                    for _ in range(rounds):
                        for n, m in group:
                            t = time.perf_counter()
                            for pts, mask in batches:
                                predict(m(pts, mask, retry=retry), mask)
                            times[n].append(time.perf_counter() - t)
                first = float(np.median(times[name]))
                for n, m in group:
                    best, median = 256 / min(times[n]), 256 / float(np.median(times[n]))
                    params = sum(p.numel() for p in m.parameters())
                    ratio = first / float(np.median(times[n]))
                    print(
                        f"| {n} | {params:,} | {retry:g} | {size} | {best:,.0f} / {median:,.0f} | {ratio:.2f} |",
                        flush=True,
                    )


def solve_section(root: Path, png: Path | None, config: SolveConfig | None = None) -> None:
    a = (config or SolveConfig()).acceleration_robust
    prior = f"acceleration prior Cauchy past {a:g} m/s^2" if a > 0 else "acceleration prior squared"
    print(f"\n## Body solve on the files' labels (stage 1 + stage 2, CPU; {prior})")
    print("| file | layout | frames | solved | residual mean / median (mm) | frames/s |\n|---|---|---|---|---|---|")
    for name, files in FILES.items():
        layout = MarkerLayout.load(name)
        for rel in files:
            seq = read(root / rel)
            lay = layout if all(x in seq.labels for x in layout.labels) else MarkerLayout.load("pig35")
            t = time.perf_counter()
            res = solve_sequence(seq, lay, config=config)
            dt = time.perf_counter() - t
            r = res.residual[torch.isfinite(res.residual)] * 1000
            solved = 100 * float(res.solved.float().mean())
            print(
                f"| {Path(rel).stem} | {lay.name} | {seq.num_frames} | {solved:.1f} % | "
                f"{float(r.mean()):.1f} / {float(r.median()):.1f} | {seq.num_frames / dt:.0f} |",
                flush=True,
            )
            if png is not None and rel.endswith("85_02.c3d"):
                frame = min(400, seq.num_frames - 1)
                render_solution(png, seq, lay, res, frame)
                print(f"wrote {png} (frame {frame}: body, observed markers in red)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--evaldata", type=Path, default=Path(__file__).resolve().parents[2] / "shared/evaldata")
    p.add_argument("--sections", nargs="+", default=["label", "body", "speed", "solve"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="first file per model, first 300 frames (a smoke test)")
    p.add_argument("--files", nargs="+", metavar="KEY", help="only the files whose name holds one of these")
    p.add_argument("--png", type=Path, default=Path("benchmarks/mocap_solve.png"))
    p.add_argument("--cmu41", default="cmu41", help="labeler weights (name or path)")
    p.add_argument("--pig39", default="pig39", help="labeler weights (name or path)")
    p.add_argument("--retry", type=float, help="two-stage labelers: override the weights' retry confidence (0: off)")
    p.add_argument("--bf16", action="store_true", help="labelers' networks in bfloat16 (Labeler.set_autocast)")
    p.add_argument(
        "--acceleration-robust",
        type=float,
        metavar="M_S2",
        help="solve section: SolveConfig.acceleration_robust (0: the squared prior of before 2026-11-29)",
    )
    p.add_argument(
        "--speed-also",
        nargs="*",
        default=[],
        metavar="NAME",
        help="labelers (names or paths) timed in the speed section beside the model of their layout",
    )
    p.add_argument("--session", nargs="*", default=[], metavar="KEY=WEIGHTS",
                   help="the files whose name holds KEY also by this session-layout labeler")  # fmt: skip
    args = p.parse_args()
    if not args.evaldata.is_dir():
        raise SystemExit(f"--evaldata: {args.evaldata} is not a folder")
    if args.quick:
        for name in FILES:
            FILES[name] = FILES[name][:2]
        global MAX_FRAMES
        MAX_FRAMES = 300
    if args.files:
        for name in list(FILES):
            FILES[name] = [f for f in FILES[name] if any(k in Path(f).stem for k in args.files)]
            if not FILES[name]:
                del FILES[name]
        if not FILES:
            raise SystemExit(f"--files: no evaluation file's name holds any of {args.files}")
    models = {k: load_labeler(getattr(args, k)) for k in FILES}
    sessions = {k: load_labeler(w) for k, _, w in (x.partition("=") for x in args.session)}
    for m in (*models.values(), *sessions.values()):
        m.eval().set_autocast(torch.bfloat16 if args.bf16 else None)
        if args.retry is not None and m.orienter is not None:
            m.config = replace(m.config, retry=args.retry)
    bf16 = ", networks in bfloat16" if args.bf16 else ""
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads{bf16}")
    if "label" in args.sections:
        label_section(args.evaldata, models, args.seed, sessions)
    if "body" in args.sections:
        body_section(args.evaldata, models, args.seed)
    if "copies" in args.sections:
        copies_section(args.evaldata, models)
    if "retry" in args.sections:
        retry_section(args.evaldata, models)
    if "speed" in args.sections:
        try:
            also = [(n, load_labeler(n).eval()) for n in args.speed_also]
        except (OSError, ValueError) as err:
            raise SystemExit(f"--speed-also: {err}") from None
        speed_section(args.evaldata, models, args.seed, also=also)
    if "solve" in args.sections:
        try:
            cfg = (
                None if args.acceleration_robust is None else SolveConfig(acceleration_robust=args.acceleration_robust)
            )
        except ValueError as err:
            p.error(f"--{str(err).replace('_', '-')}")
        solve_section(args.evaldata, args.png if cfg is None else None, cfg)


if __name__ == "__main__":
    main()
