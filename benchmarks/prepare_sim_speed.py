"""The held-out simulation's cost on a prepared capture's avatar (issue 23): the first frames of
``animate`` on the capture's held-out motion, as the ``references`` stage runs it (true material,
the 1-s warm-up from the capture's frame-1 pose), with seconds, Newton iterations and contacts
per frame.

    python benchmarks/prepare_sim_speed.py AVATAR_DIR CAPTURE [--frames 10] [--warmup 1.0]
        [--drop-true-body TRUE_CAPTURE] [--out OUT.json]

``AVATAR_DIR``: a run's ``references/avatar``. ``--drop-true-body``: first remove the garment
vertices whose nearest point of TRUE_CAPTURE's template is body (what a perfect segmentation
would leave out; the avatar is copied next to ``--out``). Run the avatars to compare one after
the other on the same machine: seconds depend on the load, iterations and contacts do not.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np


class _Stop(Exception):
    pass


def drop_true_body(avatar: Path, truth: Path, work: Path) -> tuple[Path, int]:
    from physavatar.capture import load_capture
    from physavatar.files import PlyMesh, read_ply, write_ply
    from physavatar.stages.prepare.segment import _face_submesh, transfer_labels

    tpl = load_capture(truth).template
    shutil.rmtree(work, ignore_errors=True)
    shutil.copytree(avatar, work)
    ply = read_ply(work / "template.ply")
    lab = np.asarray(ply.vertex_data["label"]).astype(np.int64)
    drop = (lab > 0) & (transfer_labels(ply.vertices, tpl.vertices, tpl.faces, tpl.labels) == 0)
    keep = ~drop[ply.faces].any(1)
    ids, F = _face_submesh(ply.faces, keep)
    assert (ids[:int((lab == 0).sum())] == np.arange(int((lab == 0).sum()))).all()  # the body first, whole
    data = {k: np.asarray(v)[ids] for k, v in ply.vertex_data.items()}
    write_ply(work / "template.ply", PlyMesh(ply.vertices[ids], F, data,
                                             ply.face_uvs[keep] if ply.face_uvs is not None else None))
    return work, int(drop.sum())


def main() -> int:
    import physavatar.stages.animate as A
    from physavatar.body.motion import Motion
    from physavatar.capture import load_capture
    from physavatar.data.avatar import Avatar

    ap = argparse.ArgumentParser()
    ap.add_argument("avatar", type=Path)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--frames", type=int, default=10, help="simulated frames (warm-up included)")
    ap.add_argument("--warmup", type=float, default=1.0)
    ap.add_argument("--drop-true-body", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    av_dir, dropped = args.avatar, None
    if args.drop_true_body is not None:
        out = args.out or Path("prepare_sim_speed.json")
        av_dir, dropped = drop_true_body(args.avatar, args.drop_true_body, out.parent / (out.stem + "_avatar"))
    av = Avatar.load(av_dir)
    held = Motion.load(load_capture(args.capture).ground_truth / "heldout" / "motion.npz")
    reports = []
    run = A.simulate_on_body

    def counted(*a, on_frame=None, **kw):
        def each(c, r):
            reports.append(r)
            print(json.dumps(r), flush=True)
            if on_frame:
                on_frame(c, r)
            if len(reports) >= args.frames:
                raise _Stop

        return run(*a, on_frame=each, **kw)

    A.simulate_on_body = counted
    t0 = time.time()
    try:
        A.animate(av, held, warmup_s=args.warmup, progress=False)
    except _Stop:
        pass
    res = {"avatar": str(args.avatar), "dropped_true_body_vertices": dropped, "seconds": round(time.time() - t0, 1),
           "frames": reports, "s_per_frame": float(np.mean([r["seconds"] for r in reports])),
           "newton_per_frame": float(np.mean([r["newton_iterations"] for r in reports])),
           "contacts_mean": float(np.mean([r["contacts"] for r in reports]))}
    print(json.dumps({k: v for k, v in res.items() if k != "frames"}))
    if args.out:
        args.out.write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
