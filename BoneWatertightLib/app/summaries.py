"""The summary lines of a run in 3D Slicer (the panel's result line, the logic's log): one for
a one-bone result, and a header, one line per bone, one per pair and the warnings of a joint
run. Plain Python on the typed results (the pipeline's, or a child run's of the same shape);
the command line's own lines are :func:`BoneWatertightLib.report.case_summary_line` and
:func:`~BoneWatertightLib.report.pair_summary_line`.
"""

from __future__ import annotations

from ..report import segment_genus_of, summary_line


def summarize(result, name: str = "") -> str:
    """The one summary line of a ReconstructionResult (panel result line, logs): vertices,
    faces, checks, distance to the constraint points and the pipeline's total time."""
    report = result.report
    return summary_line(name, report.checks, report.distance_to_constraints_mm,
                        report.timings.total, result.surface.n_vertices,
                        result.surface.n_faces, segment_genus=segment_genus_of(report))


def bone_summary(bone) -> str:
    """One line per bone of a joint run: vertices, faces, checks, plausibility, cap, warnings."""
    report = bone.report
    text = summary_line(bone.name, report.checks, report.distance_to_constraints_mm, None,
                        bone.surface.n_vertices, bone.surface.n_faces,
                        segment_genus=segment_genus_of(report))
    p = report.plausibility
    if p is not None:
        state = "plausible" if p.ok else "IMPLAUSIBLE"
        text += (f"; {state}: {100 * p.segment_inside_fraction:.0f} % of the segment inside, volume "
                 f"{p.volume_ratio:.2f} x the segment's, at most {p.max_excursion_mm:.1f} mm outside it")
    cap = report.cap or {}
    if cap.get("faces"):
        text += f"; cut by the scan: capped, {cap.get('area_mm2', 0.0):.0f} mm² of cap"
    n = len(report.warnings)
    text += f"; {n} warning{'s' if n != 1 else ''}" if n else ""
    return text


def pair_summary(pair) -> str:
    """One line per pair of bones: smallest gap, crossings, vertices inside the other."""
    gap = "no vertex within 2 mm of the other" if pair.min_gap_mm is None else \
        f"smallest gap {pair.min_gap_mm:.2f} mm"
    inside = pair.a_inside_b + pair.b_inside_a
    text = (f"{pair.a} / {pair.b}: {gap}, {pair.crossing_face_pairs} crossing face pairs, "
            f"{inside} vertices inside the other")
    if pair.contact_area_mm2:
        text += f", {pair.contact_area_mm2:.0f} mm² within 1 mm"
    return text


def summarize_joint(joint) -> list:
    """The lines of a joint run (panel result, logs): a header, one line per bone, one per pair
    of bones, then every warning (on_implausible = warn)."""
    report = joint.report
    n = len(joint.bones)
    header = f"{n} bone{'s' if n != 1 else ''} in {report.timings.total:.1f} s"
    header += "; neighbours: " + (", ".join(report.neighbours) if report.neighbours else "none")
    lines = [header] + [bone_summary(b) for b in joint.bones] + [pair_summary(p) for p in joint.pairs]
    lines += [f"warning: {w}" for b in joint.bones for w in b.report.warnings]
    return lines
