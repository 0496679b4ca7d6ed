"""The results table a headless batch prints (`station serve --once`, `station demo --once`): per
DUT the calibration result (or SFEM residuals, or the fault), the verdict and, for a verified
profile, what was programmed and the verified drift error; with the simulated truth beside it when
there is one (the demo). Also the same numbers as a dict (`station demo --json`)."""

from __future__ import annotations

from contracts.types import AXES


def results_table(status: dict, truths: dict | None = None) -> tuple[str, dict]:
    """Text table of a batch's per-DUT results (and errors vs truth); also the numbers as a dict."""
    lines = []
    head = f"{'slot':5} {'serial':14} {'state':9} " + " ".join(f"TDB{a}" .rjust(8) for a in AXES) + " " + \
        " ".join(f"TDSF{a}".rjust(8) for a in AXES)
    if truths:
        head += "  max|dTDB| max|dTDSF|"
    lines.append(head)
    summary: dict = {"batch": status["id"], "state": status["state"], "error": status["error"], "duts": {}}
    for s in status["slots"]:
        res = s.get("result") or {}
        axes = res.get("axes") or {}
        row = f"{s['slot']:5} {str(s['serial'] or '-'):14} {s['state']:9} "
        entry: dict = {"serial": s["serial"], "state": s["state"], "fault_reason": s["fault_reason"]}
        if axes:
            tdb = [axes[a]["tdb_mg_per_c"] for a in AXES]
            tdsf = [axes[a]["tdsf_ppm_per_c"] for a in AXES]
            row += " ".join(f"{v:8.4f}" for v in tdb) + " " + " ".join(f"{v:8.1f}" for v in tdsf)
            entry.update(tdb_mg_per_c=tdb, tdsf_ppm_per_c=tdsf)
            t = truths.get(s["slot"]) if truths else None
            if t is not None:
                e_tdb = max(abs(a - b) for a, b in zip(tdb, list(t.tdb_mg_per_c)))
                e_tdsf = max(abs(a - b) for a, b in zip(tdsf, list(t.tdsf_ppm_per_c)))
                row += f"  {e_tdb:9.4f} {e_tdsf:9.1f}"
                entry.update(err_tdb_mg_per_c=e_tdb, err_tdsf_ppm_per_c=e_tdsf,
                             true_tdb_mg_per_c=[float(x) for x in t.tdb_mg_per_c],
                             true_tdsf_ppm_per_c=[float(x) for x in t.tdsf_ppm_per_c])
        elif res.get("steps"):  # SFEM (sfem-24, contracts/sfem_result.py): the residual before -> after per step
            temps = res["steps"]
            row += "SFEM " + "  ".join(
                f"{t['temp_c']:.0f} C: {t['rmse_before_mg']:.1f} -> {t['rmse_after_mg']:.2f} mg" for t in temps)
            entry["sfem"] = [{"temp_c": t["temp_c"], "rmse_before_mg": t["rmse_before_mg"],
                              "rmse_after_mg": t["rmse_after_mg"], "rmse_heldout_mg": t.get("rmse_heldout_mg")}
                             for t in temps]
        elif s["fault_reason"]:
            row += s["fault_reason"]
        v = s.get("decision")
        if v:  # the station's decision (station/decisions/verdicts.py)
            row += f"  {v['verdict'].upper()} {v.get('grade') or ''} ({v.get('reason') or ''})"
            entry.update(verdict=v["verdict"], grade=v.get("grade"), tray=v.get("tray"), reason=v.get("reason"),
                         attempt=v.get("attempt"))
        lines.append(row)
        pv = program_verify_summary(s.get("program"), s.get("verification"))
        if pv is not None:
            entry["program_verify"] = pv
            lines.append(" " * 6 + program_verify_line(pv))
        summary["duts"][s["slot"]] = entry
    return "\n".join(lines), summary


def program_verify_summary(program: dict | None, verification: dict | None) -> dict | None:
    """Program and verify of one DUT as the demo reports it (None: the profile has no program step)."""
    if not program:
        return None
    ver = verification or {}
    return {
        "programmed": bool(program.get("programmed")),
        "crc": program.get("crc"),
        "readback_crc": program.get("readback_crc"),
        "crc_match": bool(program.get("readback_identical")),
        "comp_on": bool(program.get("comp")),
        "attempts": program.get("attempts"),
        "error_kind": program.get("error_kind"),
        "error": program.get("error"),
        "written_tdb_mg_per_c": program.get("tdb_mg_per_c"),
        "written_tdsf_ppm_per_c": program.get("tdsf_ppm_per_c"),
        "verified": ver.get("passed") if verification else None,
        "e_before_mg": ver.get("e_before_mg"),
        "e_after_mg": ver.get("e_after_mg"),
        "flags": list(ver.get("flags") or []),
    }


def program_verify_line(pv: dict) -> str:
    """One table line: what was written and proven, and the verified drift error per axis."""
    if not pv["programmed"]:
        return f"program: NOT programmed ({pv.get('error_kind') or '-'}: {pv.get('error') or '-'})"
    text = (f"program: CRC {pv['crc']} {'= read back' if pv['crc_match'] else '!= read back ' + str(pv['readback_crc'])}"
            f", compensation {'on' if pv['comp_on'] else 'OFF'}, {pv['attempts']} attempt(s)")
    after, before = pv.get("e_after_mg") or {}, pv.get("e_before_mg") or {}
    if pv["verified"] is None:
        return text + "; not verified"
    per_axis = " ".join(f"{a} {_mg(after.get(a))} (was {_mg(before.get(a))})" for a in AXES)
    return text + f"; verified E after [mg]: {per_axis}: {'PASS' if pv['verified'] else 'FAIL'}"


def _mg(v) -> str:
    return "-" if v is None else f"{float(v):.2f}"


__all__ = ["program_verify_line", "program_verify_summary", "results_table"]
