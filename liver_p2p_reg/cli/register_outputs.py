"""The register command's outputs besides the JSON: the moved (or deformed) surface, the overlay plot, the summary line."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from liver_p2p_reg.errors import InputError


def source_mesh(path: Path) -> tuple[Any, Any] | None:
    """SOURCE's vertices (mm) and triangles when it is a mesh file with faces, else None (points only)."""
    from liver_p2p_reg.cloud_io import load_mesh

    try:
        vertices, triangles = load_mesh(path, warn=False)  # load_points has read SOURCE and warned already
    except InputError:
        return None
    return (vertices, triangles) if len(triangles) else None


def write_extras(source, target, result, config, warnings, fid_s, fid_t, moved: Path | None, plot: Path | None):
    written = []
    if moved is not None:
        from liver_p2p_reg.cloud_io import save_points
        from liver_p2p_reg.metrics import transform_points

        deformation = result.deformation
        if deformation is not None and deformation.applied:  # the deformed surface, where the organ now is
            save_points(moved, deformation.deformed_position_mm(source))
        else:
            save_points(moved, transform_points(result.T_target_source, source))
        written.append(moved)
    if plot is not None:
        from liver_p2p_reg.overlay import plot_registration

        plot_registration(
            source,
            target,
            result,
            plot,
            warnings=warnings,
            residual_warn_mm=config.residual_warn_mm,
            source_fiducials_mm=fid_s,
            target_fiducials_mm=fid_t,
        )
        written.append(plot)
    return written


def summary_line(target: Path, payload: dict, output: Path | None, written: list[Path]) -> str:
    """One line a person reads: status, fit, confidence, time and where the results went."""
    parts = [f"residual {payload['residual_mm']:.2f} mm"]
    if "deformation" in payload:
        d = payload["deformation"]
        bound = payload.get("deformed_error_bound_mm")
        within = f", interior within {bound:.1f} mm" if d["applied"] and bound is not None else ""
        if within and payload.get("deformed_error_calibration_note"):  # the JSON's caveat, said here too
            within += " (calibrated for other settings: coverage unknown)"
        parts.append(
            f"deformed {d['rms_displacement_mm']:.1f} mm RMS{within}"
            if d["applied"]
            else f"not deformed ({d['reason']})"
        )
    if payload.get("uncertainty_mm") is not None:
        parts.append(f"uncertainty {payload['uncertainty_mm']:.1f} mm")
    if payload.get("rms_tre_mm") is not None:
        parts.append(f"RMS-TRE {payload['rms_tre_mm']:.2f} mm")
    if payload.get("visibility") is not None:
        parts.append(f"visibility {payload['visibility']:.2f}")
    if payload.get("structures"):
        n, bounds = len(payload["structures"]), [s["max_error_bound_mm"] for s in payload["structures"]]
        known = [b for b in bounds if b is not None]  # none without an error model
        caveat = " (calibrated for other settings: coverage unknown)" if payload.get("error_calibration_note") else ""
        parts.append(
            f"{n} structure{'s' if n > 1 else ''}" + (f", error bound <= {max(known):.1f} mm{caveat}" if known else "")
        )
    parts.append(f"{payload['runtime_ms']['total']:.0f} ms")
    where = [f"JSON -> {output}" if output is not None else "JSON on stdout", *(str(p) for p in written)]
    line = f"{target.name}: {payload['status']} {payload['method']}: {', '.join(parts)}; {', '.join(where)}"
    if payload["warnings"]:
        line += f" ({len(payload['warnings'])} warning{'s' if len(payload['warnings']) > 1 else ''} on stderr)"
    return line
