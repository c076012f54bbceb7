"""The estimate output folder: ``<method>.tum``, ``trajectory.csv``, ``report.json``, refined map.

This is the one module that reads and writes ``trajectory.csv`` and
``report.json`` (TUM goes through ``signpose.io.tum``). Every file is written
atomically.

trajectory.csv: one row per frame and method, header
``method,frame,t_s,x_m,y_m,z_m,qw,qx,qy,qz,sigma_x_m,sigma_y_m,sigma_z_m,signs_used,status``
(the unit of each column in its name); t in seconds, position of the camera
centre in the world [m], rotation world_R_cam as a unit quaternion (w first),
position sigma per world axis [m]; empty pose/sigma fields where the
method has no pose or no sigma (never NaN); status is a token: ``ok``,
``weak``, ``bridged`` or ``suspect`` for a pose (see
``estimator.status.PoseStatus``), else why there is none (``few_signs``,
``collinear``, ...: ``estimator.perframe.PoseFailure``), never free text.
``read_trajectory_csv`` also reads the header before units were added
(``t,x,y,z,...,sigma_z``) and returns the columns under the new names.

report.json: settings, versions (from the installed packages' metadata), per
method coverage with the share of each status token and the weak poses'
worst-axis sigma, timing, the outliers
(down-weighted, mis-decoded, and ``rejected``: each observation left out with
the test that rejected it: ``pnp_gate``, ``innovation``, ``tukey`` or
``gnc``), the motion prior chosen from the flight, and after ``compare_dir``
the metrics against ground truth (``estimator.metrics.Metrics``: keys carry
their unit, ``mae_xyz_m``, ``ate_rmse_m``, ``rot_rmse_deg``, ...).

map_refined.yaml (with the smoother): the map refined from the flight, in
the map schema (``maps/SCHEMA.md``); map_refined.json beside it: per sign the
posterior sigma, frames seen and the move against the survey
(``write_refined_map``, also the writer of ``refine-map``).
"""

from __future__ import annotations

import csv
import importlib.metadata
import io
import json
import platform
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from signpose.core.errors import InputError
from signpose.core.fileio import atomic_write, ensure_dir
from signpose.estimator.estimate import EstimateResult, MethodEstimate
from signpose.estimator.metrics import compute_metrics, format_table
from signpose.estimator.refine import MOVED_SIGMAS, RefinedMap
from signpose.estimator.status import PoseStatus
from signpose.estimator.trajectory import Trajectory, quat_xyzw_from_rotation
from signpose.io.groundtruth import check_time_overlap, read_ground_truth
from signpose.io.tum import read_tum, write_tum
from signpose.maps.loader import write_map

CSV_HEADER = (
    "method",
    "frame",
    "t_s",
    "x_m",
    "y_m",
    "z_m",
    "qw",
    "qx",
    "qy",
    "qz",
    "sigma_x_m",
    "sigma_y_m",
    "sigma_z_m",
    "signs_used",
    "status",
)
# The header written before the units were named (read, never written).
_OLD_CSV_HEADER = (
    "method",
    "frame",
    "t",
    "x",
    "y",
    "z",
    "qw",
    "qx",
    "qy",
    "qz",
    "sigma_x",
    "sigma_y",
    "sigma_z",
    "signs_used",
    "status",
)
MAX_LISTED_OUTLIERS = 2000
# Distribution name of each package in report.json's "versions" (cv2 is opencv's module).
_DISTRIBUTIONS = {
    "signpose": ("signpose",),
    "gtsam": ("gtsam",),
    "cv2": ("opencv-python-headless", "opencv-python", "opencv-contrib-python"),
    "numpy": ("numpy",),
}


def method_trajectory(m: MethodEstimate) -> Trajectory:
    """The method's posed frames as a Trajectory."""
    return Trajectory.from_matrices(m.stamps_s[m.valid], m.world_T_cam[m.valid])


def package_version(names: tuple[str, ...]) -> str:
    """Version of the first installed distribution of ``names`` ("unknown" when none is)."""
    for name in names:
        try:
            return importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            continue
    return "unknown"


def _versions() -> dict:
    # Package metadata, not ``module.__version__``: gtsam's module has none.
    out = {"python": platform.python_version()}
    out |= {mod: package_version(dists) for mod, dists in _DISTRIBUTIONS.items()}
    return out


def _clean(x):
    """JSON-safe: NaN/inf -> None, numpy scalars -> Python."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def _csv_text(result: EstimateResult) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_HEADER)
    for name, m in result.methods.items():
        quats = quat_xyzw_from_rotation(m.world_T_cam[:, :3, :3])
        for i in range(len(m.stamps_s)):
            row = [name, int(result.frames[i]), f"{m.stamps_s[i]:.9f}"]
            if m.valid[i]:
                p = m.world_T_cam[i, :3, 3]
                q = quats[i]
                row += [f"{v:.6f}" for v in p] + [f"{v:.9f}" for v in (q[3], q[0], q[1], q[2])]
            else:
                row += [""] * 7
            sig = m.sigma_xyz[i]
            row += [f"{v:.6f}" if (m.valid[i] and np.isfinite(v)) else "" for v in sig]
            row += [int(m.signs_used[i]), m.status[i].value]
            w.writerow(row)
    return buf.getvalue()


def status_shares(m: MethodEstimate) -> dict[str, float]:
    """Share of frames with each status or failure token, in PoseStatus order first."""
    n = max(len(m.status), 1)
    tokens = [st.value for st in m.status]
    order = [st.value for st in PoseStatus] + sorted(set(tokens) - {st.value for st in PoseStatus})
    return {t: tokens.count(t) / n for t in order if t in tokens or t in ("ok", "weak")}


def _weak_poses(result: EstimateResult, m: MethodEstimate) -> list[dict]:
    """Frame and worst-axis sigma of each weak pose (the sigma is null when not computed)."""
    return [
        {"frame": int(result.frames[i]), "worst_sigma_m": float(np.max(m.sigma_xyz[i]))}
        for i, st in enumerate(m.status)
        if st is PoseStatus.WEAK
    ][:MAX_LISTED_OUTLIERS]


def status_line(result: EstimateResult) -> str:
    """One line: each method's share of ok / weak / bridged / suspect poses."""
    parts = []
    for name, m in result.methods.items():
        shares = status_shares(m)
        parts.append(f"{name} " + " ".join(f"{k} {100 * v:.1f}%" for k, v in shares.items()))
    return "status: " + "; ".join(parts)


def survey_share(m: MethodEstimate) -> dict | None:
    """The survey's share of a method's pose variance (report.json ``survey_share``):
    the part of the error shared by every frame that sees the same signs, so a
    flight's poses can all sit 2-3 sigma off together in an unlucky survey
    (scripts/eval_flight.py ``--survey-response``)."""
    if m.survey_sigma_xyz is None:
        return None
    ok = m.valid & np.all(np.isfinite(m.sigma_xyz), axis=1) & np.all(m.sigma_xyz > 0, axis=1)
    if not ok.any():
        return None
    var = np.sum(m.sigma_xyz[ok] ** 2, axis=1)
    share = np.sum(m.survey_sigma_xyz[ok] ** 2, axis=1) / var
    return {
        "of_variance_median": round(float(np.median(share)), 3),
        "sigma_m_median_xyz": np.median(m.survey_sigma_xyz[ok], axis=0).round(4).tolist(),
        "note": (
            "the map's survey error is this share of each pose's variance and is the same "
            "for every frame that sees the same signs: the poses' errors move together, not "
            "frame by frame"
        ),
    }


def report_dict(result: EstimateResult) -> dict:
    """The content of report.json (before any metrics are added)."""
    n = len(result.frames)
    seen = result.signs_seen > 0
    coverage = {}
    for name, m in result.methods.items():
        coverage[name] = {
            "frames": n,
            "posed": int(m.valid.sum()),
            "coverage": float(m.valid.mean()) if n else 0.0,
            "coverage_of_frames_with_signs": float(m.valid[seen].mean()) if seen.any() else None,
            "bridged": int(sum(s is PoseStatus.BRIDGED for s in m.status)),
            "status": status_shares(m),
            "weak": _weak_poses(result, m),
        }
        share = survey_share(m)
        if share is not None:
            coverage[name]["survey_share"] = share
    o = result.outliers.to_dict()
    o["n_downweighted"] = len(o["downweighted"])
    o["n_rejected"] = {
        test: sum(r["test"] == test for r in o["rejected"])
        for test in sorted({r["test"] for r in o["rejected"]})
    }
    o["downweighted"] = sorted(o["downweighted"], key=lambda d: -d["residual_px"])[
        :MAX_LISTED_OUTLIERS
    ]
    return _clean(
        {
            "settings": result.settings.to_dict(),
            "versions": _versions(),
            "frames": n,
            "frames_with_signs": int(seen.sum()),
            "coverage": coverage,
            "timing_s": result.timing_s,
            "outliers": o,
            "motion_prior": result.motion.to_dict() if result.motion is not None else None,
            "pixel_noise_scale": result.pixel_noise_scale,
            "pose_noise_scale": result.pose_noise_scale,
            **({"warnings": list(result.warnings)} if result.warnings else {}),
            **(
                {"intrinsics_check": result.intrinsics.as_dict()}
                if result.intrinsics is not None
                else {}
            ),
        }
    )


def write_json(path: Path, data: dict) -> None:
    with atomic_write(path) as f:
        json.dump(_clean(data), f, indent=2)
        f.write("\n")


REFINED_MAP = "map_refined.yaml"


def write_refined_map(
    path: str | Path, refined: RefinedMap, survey: str, flights: list[str]
) -> list[Path]:
    """Write the refined map (map schema, ``path``) and ``<path>.json`` beside it.

    The YAML is a map ``load_map`` reads (refined centres, the map's
    orientations, posterior sigma_m); the JSON holds per sign its refined and
    survey centre, posterior sigma, frames seen and how far it moved, and the
    signs moved by more than ``MOVED_SIGMAS`` survey sigmas. Returns both paths.
    """
    path = Path(path)
    write_map(path, refined.sign_map)
    report = path.with_suffix(".json")
    write_json(
        report,
        {
            "survey": survey,
            "flights": flights,
            "signs": [s.to_dict() for s in refined.signs],
            "moved": list(refined.moved),
            "moved_sigmas": MOVED_SIGMAS,
        },
    )
    return [path, report]


def write_outputs(
    out_dir: str | Path, result: EstimateResult, refined: RefinedMap | None = None
) -> list[Path]:
    """Write ``<method>.tum`` for every method, trajectory.csv and report.json.

    TUM files hold only the frames with a pose. With ``refined`` (see
    ``estimator.refine.refine_flight``) also ``map_refined.yaml`` and
    ``map_refined.json``. Returns the paths written.
    """
    out = ensure_dir(out_dir)
    written = []
    for name, m in result.methods.items():
        p = out / f"{name}.tum"
        write_tum(p, method_trajectory(m))
        written.append(p)
    p = out / "trajectory.csv"
    with atomic_write(p) as f:
        f.write(_csv_text(result))
    written.append(p)
    p = out / "report.json"
    write_json(p, report_dict(result))
    written.append(p)
    if refined is not None:
        survey = refined.sign_map.source or "map"
        written += write_refined_map(out / REFINED_MAP, refined, survey, [])
    return written


def read_trajectory_csv(path: str | Path) -> dict[str, dict[str, np.ndarray]]:
    """trajectory.csv back as method -> column -> array (empty fields -> NaN).

    Columns are named as in ``CSV_HEADER`` (``t_s``, ``x_m``, ...), also for a
    file with the header from before the units were named.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror})") from None
    rows = list(csv.reader(io.StringIO(text)))
    if not rows or tuple(rows[0]) not in (CSV_HEADER, _OLD_CSV_HEADER):
        raise InputError(f"{p}: not a signpose trajectory.csv (wrong header)")
    out: dict[str, dict[str, list]] = {}
    for lineno, r in enumerate(rows[1:], start=2):
        if len(r) != len(CSV_HEADER):
            raise InputError(f"{p}: line {lineno}: expected {len(CSV_HEADER)} fields")
        cols = out.setdefault(r[0], {k: [] for k in CSV_HEADER[1:]})
        for k, v in zip(CSV_HEADER[1:], r[1:], strict=True):
            cols[k].append(v)
    result: dict[str, dict[str, np.ndarray]] = {}
    for name, cols in out.items():
        d: dict[str, np.ndarray] = {}
        for k, vals in cols.items():
            if k == "status":
                d[k] = np.array(vals, dtype=object)
            elif k in ("frame", "signs_used"):
                d[k] = np.array([int(v) for v in vals], dtype=np.int64)
            else:
                d[k] = np.array([float(v) if v else np.nan for v in vals])
        result[name] = d
    return result


def read_report(path: str | Path) -> dict:
    p = Path(path)
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{p}: report.json not found; run 'signpose estimate' first") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{p}: cannot read report ({exc})") from None


def method_files(out_dir: str | Path, exclude: str | Path | None = None) -> dict[str, Path]:
    """method name -> TUM file of an estimate folder (known methods first, ``exclude`` left out)."""
    d = Path(out_dir)
    if not d.is_dir():
        raise InputError(f"{d}: not a folder; pass the --out folder of 'signpose estimate'")
    skip = Path(exclude).resolve() if exclude is not None else None
    files = {
        p.stem: p
        for p in sorted(d.glob("*.tum"))
        if p.stem not in ("groundtruth", "gt") and p.resolve() != skip
    }
    order = ["baseline", "pnp", "smoothed", "causal"]
    ranked = {k: files[k] for k in order if k in files}
    ranked.update({k: v for k, v in files.items() if k not in ranked})
    if not ranked:
        raise InputError(f"{d}: no <method>.tum files; run 'signpose estimate --out {d}' first")
    return ranked


def compare_dir(
    out_dir: str | Path, gt_path: str | Path, gt_offset_s: float = 0.0
) -> dict[str, dict]:
    """Metrics of every method in ``out_dir`` against ``gt_path``; added to report.json.

    Args:
        out_dir: an estimate folder.
        gt_path: ground truth TUM file.
        gt_offset_s: added to the ground truth's stamps [s] (``--gt-offset``).

    Returns:
        method -> Metrics.to_dict(); report.json gets a ``"metrics"`` entry
        (rewritten atomically; created if missing) whose table has each
        method's pose status shares when report.json records them.

    Raises:
        InputError: the ground truth shares no stamps with the trajectories or
            covers under half of their time span (both ranges in the message).
    """
    gt = read_ground_truth(gt_path, gt_offset_s)
    trajs = {name: read_tum(p) for name, p in method_files(out_dir, gt_path).items()}
    stamps_s = np.concatenate([t.stamps_s for t in trajs.values()])
    check_time_overlap(stamps_s, f"{out_dir} ({', '.join(trajs)})", gt, gt_path)
    metrics = {
        name: compute_metrics(t, gt, reference_stamps_s=stamps_s) for name, t in trajs.items()
    }
    out = {name: m.to_dict() for name, m in metrics.items()}
    report_path = Path(out_dir) / "report.json"
    report = read_report(report_path) if report_path.exists() else {}
    report["metrics"] = {
        "groundtruth": str(gt_path),
        "methods": out,
        "table": format_table(metrics, recorded_status(report)),
    }
    write_json(report_path, report)
    return out


def recorded_status(report: Mapping) -> dict[str, dict[str, float]] | None:
    """method -> share of each pose status token, from report.json's coverage (None: none)."""
    coverage = report.get("coverage")
    if not isinstance(coverage, Mapping):
        return None
    shares = {
        name: c["status"]
        for name, c in coverage.items()
        if isinstance(c, Mapping) and isinstance(c.get("status"), Mapping)
    }
    return shares or None


def metrics_table(out_dir: str | Path) -> str:
    """The table stored by the last ``compare_dir`` call."""
    return read_report(Path(out_dir) / "report.json")["metrics"]["table"]
