#!/usr/bin/env python3
"""Summarises a run of tools/scripts/gpu-check.sh: gpu-check.json and gpu-check.md.

Reads the script's scratch folder (steps.tsv, logs/, runs/*/summary.json, the bind_cost
CSVs, step 2's validation-messages.tsv, step 4's report) and writes the two summaries
into --out. Standard library only; gpu-check.sh falls back to a plain step table when
python3 is missing or this fails.

The summary.json keys read are the flythrough's (tools/flythrough/src/output.rs and
streaming/src/bench/stats.rs): device, texture_backing, validation_errors, frames,
frame_ms, wall_s, duration_s, wall_ms_per_frame, gpu_pass_ms, meshes_drawn,
meshes_culled, bytes_streamed, psnr_of_mean_mse_db, error_frames, evicted_layers,
dropped_levels, frames_over_budget, peak_resident_bytes, memory_budget_bytes, policy,
blocks_bound. A key a run lacks shows as null (JSON) or "-" (Markdown).
"""

import argparse
import csv
import datetime
import json
import os
import re
import sys

PASSES = ["uploads", "feedback", "compaction", "visible", "cull"]


def read_steps(work):
    rows = []
    with open(os.path.join(work, "steps.tsv"), encoding="utf-8", errors="replace") as f:
        header = f.readline().rstrip("\n").split("\t")
        for line in f:
            fields = line.rstrip("\n").split("\t")
            row = dict(zip(header, fields + [""] * (len(header) - len(fields))))
            rows.append({k: (None if v in ("", "-") else v) for k, v in row.items()})
    for row in rows:
        row["rc"] = int(row["rc"]) if row.get("rc") not in (None,) and re.fullmatch(r"-?\d+", row["rc"]) else None
        for key in ("seconds", "estimate_s"):
            try:
                row[key] = float(row[key]) if row.get(key) is not None else None
            except ValueError:
                row[key] = None
        params = {}
        for part in (row.get("params") or "").split(";"):
            if "=" in part:
                k, v = part.split("=", 1)
                params[k] = v
        row["params"] = params
    return rows


def read_text(path, limit=None):
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            return f.read() if limit is None else f.read(limit)
    except OSError:
        return None


def read_json(path):
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


def get(d, *keys):
    for k in keys:
        if not isinstance(d, dict):
            return None
        d = d.get(k)
    return d


def fmt(x, digits=2):
    if x is None:
        return "-"
    if isinstance(x, bool):
        return str(x).lower()
    if isinstance(x, int):
        return f"{x:,}"
    if isinstance(x, float):
        return f"{x:,.{digits}f}"
    return str(x).replace("|", "\\|")


def log_tail(work, step_id, lines=12):
    text = read_text(os.path.join(work, "logs", f"{step_id}.log"))
    if not text:
        return []
    out = [l for l in text.splitlines() if l.strip()]
    # The error and what led to it, not the status lines.
    errors = [i for i, l in enumerate(out) if l.startswith(("Error", "error", "thread ")) or "panicked" in l]
    if errors:
        return out[errors[0] : errors[0] + lines]
    return out[-lines:]


def parse_vulkaninfo(text):
    """GPU blocks of `vulkaninfo --summary`: a dict of key = value per device."""
    devices, current = [], None
    for line in (text or "").splitlines():
        if re.match(r"^GPU\d+:", line.strip()):
            current = {}
            devices.append(current)
        elif current is not None:
            m = re.match(r"^\s*(\w+)\s*=\s*(.*?)\s*$", line)
            if m:
                current[m.group(1)] = m.group(2)
    return devices


def parse_bind_csv(path):
    rows = []
    try:
        with open(path, encoding="utf-8") as f:
            for r in csv.DictReader(f):
                row = {}
                for k, v in r.items():
                    try:
                        row[k] = float(v) if "." in v else int(v)
                    except (TypeError, ValueError):
                        row[k] = v
                rows.append(row)
    except OSError:
        pass
    return rows


def device_section(work, step):
    log = read_text(os.path.join(work, "logs", "1.log")) or ""
    lines = log.splitlines()
    device = next((l[len("device:") :].strip() for l in lines if l.startswith("device:")), None)
    return {
        "device": device,
        "nvidia_smi": (read_text(os.path.join(work, "logs", "1-nvidia-smi.txt")) or "").strip() or None,
        "vulkaninfo": parse_vulkaninfo(read_text(os.path.join(work, "logs", "1-vulkaninfo.txt"))),
        "sparse_support": next((l for l in lines if l.startswith("sparseAddressSpaceSize")), None),
        # One line per format and layer size: block bytes, granularity, flags and tail as
        # the bench prints them (engine/benches/bind_cost.rs).
        "sparse_shapes": [l for l in lines if "layers:" in l and not l.startswith("image:")],
        "bench_image": next((l for l in lines if l.startswith("image:")), None),
    }


def run_figures(run_dir):
    s = read_json(os.path.join(run_dir, "summary.json")) if run_dir else None
    if s is None:
        return None
    gpu = s.get("gpu_pass_ms")
    passes = {}
    if isinstance(gpu, dict):
        for p in PASSES:
            passes[p] = gpu.get(p)
    medians = [get(passes, p, "median") for p in PASSES]
    means = [get(passes, p, "mean") for p in PASSES]
    duration = s.get("duration_s")
    streamed = s.get("bytes_streamed")
    return {
        "device": s.get("device"),
        "texture_backing": s.get("texture_backing"),
        "policy": s.get("policy"),
        "clock": s.get("clock"),
        "width": s.get("width"),
        "height": s.get("height"),
        "culling": s.get("culling"),
        "frames": s.get("frames"),
        "duration_s": duration,
        "wall_s": s.get("wall_s"),
        "wall_ms_per_frame": s.get("wall_ms_per_frame"),
        "frame_ms": s.get("frame_ms"),
        "gpu_pass_ms": passes if passes else None,
        "gpu_ms_per_frame_median_sum": sum(m for m in medians if m is not None) if gpu else None,
        "gpu_ms_per_frame_mean_sum": sum(m for m in means if m is not None) if gpu else None,
        "meshes_drawn": s.get("meshes_drawn"),
        "meshes_culled": s.get("meshes_culled"),
        "cull_overflow_frames": s.get("cull_overflow_frames"),
        "bytes_streamed": streamed,
        "mb_per_path_s": (streamed / duration / 2**20) if streamed is not None and duration else None,
        "psnr_of_mean_mse_db": s.get("psnr_of_mean_mse_db"),
        "psnr_db": s.get("psnr_db"),
        "error_frames": s.get("error_frames"),
        "validation_errors": s.get("validation_errors"),
        "blocks_bound": s.get("blocks_bound"),
        "mips_streamed": s.get("mips_streamed"),
        "peak_resident_bytes": s.get("peak_resident_bytes"),
        "memory_budget_bytes": s.get("memory_budget_bytes"),
        "evicted_layers": s.get("evicted_layers"),
        "dropped_levels": s.get("dropped_levels"),
        "frames_over_budget": s.get("frames_over_budget"),
        "textures_failed": s.get("textures_failed"),
        # Per cache format: first_level, bytes_per_tail, single, synthetic, held_bytes
        # (absent from builds before mip-tail binding).
        "cache_tails": s.get("cache_tails"),
    }


def validation_messages(run_dir):
    rows = []
    text = read_text(os.path.join(run_dir, "validation-messages.tsv")) if run_dir else None
    for line in (text or "").splitlines():
        parts = line.split("\t")
        if len(parts) >= 3 and parts[0].isdigit():
            rows.append({"count": int(parts[0]), "severity": parts[1], "id": parts[2]})
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--budget", type=float, required=True)
    ap.add_argument("--spent", type=float, required=True)
    ap.add_argument("--pack", default=".gpu-check")
    a = ap.parse_args()

    steps = read_steps(a.work)
    for s in steps:
        if s["state"] in ("failed", "timed-out"):
            s["log_tail"] = log_tail(a.work, s["id"])
        if s.get("kind") in ("validation", "passes", "latency"):
            s["figures"] = run_figures(s.get("run_dir"))
        if s.get("kind") == "validation":
            s["validation_messages"] = validation_messages(s.get("run_dir"))
        if s.get("kind") in ("device", "bind") and s.get("run_dir"):
            s["bind_cost"] = parse_bind_csv(os.path.join(s["run_dir"], "bind_cost.csv"))

    pack_info = read_text(os.path.join(a.pack, "PACK_INFO"))
    result = {
        "written": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "budget_s": a.budget,
        "spent_s": a.spent,
        "pack_info": pack_info.strip().splitlines() if pack_info else None,
        "device": device_section(a.work, steps),
        "failed": any(s["state"] in ("failed", "timed-out") for s in steps),
        "steps": [{k: v for k, v in s.items() if k != "run_dir"} for s in steps],
    }
    with open(os.path.join(a.out, "gpu-check.json"), "w", encoding="utf-8") as f:
        json.dump(result, f, indent=2)
        f.write("\n")

    md = []
    dev = result["device"]
    md.append("# GPU check\n")
    md.append(
        f"Written {result['written']}; budget {a.budget:.0f} s, spent {a.spent:.0f} s. "
        f"{'A step failed.' if result['failed'] else 'No step that ran failed.'}\n"
    )
    if pack_info:
        md.append("Pack: " + "; ".join(pack_info.strip().splitlines()) + "\n")
    md.append("## Steps\n")
    md.append("| id | what | state | exit | s | estimate s | note |")
    md.append("|---|---|---|---:|---:|---:|---|")
    for s in steps:
        md.append(
            f"| {s['id']} | {fmt(s['title'])} | {s['state']} | {fmt(s['rc'])} | {fmt(s['seconds'], 1)} | "
            f"{fmt(s['estimate_s'], 0)} | {fmt((s.get('note') or '')[:200])} |"
        )

    md.append("\n## 1. Device, driver, sparse shapes\n")
    md.append(f"- device (the engine's pick): {fmt(dev['device'])}")
    if dev["nvidia_smi"]:
        md.append(f"- nvidia-smi (name, driver, memory): {dev['nvidia_smi']}")
    for i, v in enumerate(dev["vulkaninfo"]):
        keys = ["deviceName", "deviceType", "apiVersion", "driverVersion", "driverName", "driverInfo", "conformanceVersion"]
        md.append(f"- vulkaninfo GPU{i}: " + ", ".join(f"{k} {v[k]}" for k in keys if k in v))
    if dev["sparse_support"]:
        md.append(f"- {dev['sparse_support']}")
    if dev["sparse_shapes"]:
        md.append("\nEach cache format's block, granularity and mip tail (bind_cost's own lines):\n")
        md.append("```")
        md.extend(dev["sparse_shapes"])
        md.append("```")

    for s in (s for s in steps if s.get("kind") == "validation"):
        f = s.get("figures") or {}
        md.append("\n## 2. Default city, sparse backing, validation\n")
        md.append(f"State {s['state']}, exit status {fmt(s['rc'])}, {fmt(s['seconds'], 1)} s.\n")
        if f:
            md.append(f"- device: {fmt(f['device'])}; texture backing: {fmt(f['texture_backing'])}")
            md.append(
                f"- frames: {fmt(f['frames'])} over {fmt(f['duration_s'], 1)} path s; wall {fmt(f['wall_s'], 1)} s"
            )
            md.append(f"- validation errors (summary.json): {fmt(f['validation_errors'])}")
            md.append(
                f"- PSNR of the mean MSE against the fully resident reference: {fmt(f['psnr_of_mean_mse_db'])} dB "
                f"(per-frame PSNR median {fmt(get(f, 'psnr_db', 'median'))} dB; "
                f"{fmt(get(f, 'error_frames', 'measured'))} frames measured, "
                f"{fmt(get(f, 'error_frames', 'identical'))} identical)"
            )
            md.append(f"- blocks bound: {fmt(f['blocks_bound'])}; mips streamed: {fmt(f['mips_streamed'])}")
            tails = f.get("cache_tails")
            if isinstance(tails, list):
                for t in tails:
                    if not isinstance(t, dict):
                        continue
                    if t.get("first_level") is None:
                        md.append(f"- {fmt(t.get('format'))}: no mip tail")
                        continue
                    md.append(
                        f"- {fmt(t.get('format'))}: mip tail from level {fmt(t.get('first_level'))}, "
                        f"{fmt(t.get('bytes_per_tail'))} B per {'image (single)' if t.get('single') else 'layer'}"
                        f"{', synthetic' if t.get('synthetic') else ''}; {fmt(t.get('held_bytes'))} B held at the end"
                    )
            else:
                md.append("- mip tails: not in summary.json (a build before mip-tail binding)")
        else:
            md.append("No summary.json: the run stopped before its end.")
        msgs = s.get("validation_messages") or []
        if msgs:
            md.append("\nValidation messages printed (count, severity, id):\n")
            md.append("| count | severity | id |\n|---:|---|---|")
            for m in msgs[:30]:
                md.append(f"| {m['count']} | {m['severity']} | {fmt(m['id'])} |")
        elif s["state"] != "skipped":
            md.append("\nNo validation message printed.")

    passes = [s for s in steps if s.get("kind") == "passes"]
    if passes:
        md.append("\n## 3. GPU ms per pass, wall ms per frame, meshes drawn\n")
        md.append(
            "Fixed clock, bind latency none, no image-error reference; GPU ms are the median per frame "
            "(timestamps), `gpu` their sum.\n"
        )
        md.append(
            "| run | state | backing | frames | "
            + " | ".join(PASSES)
            + " | gpu ms | wall ms/frame | meshes drawn median / max | culled median |"
        )
        md.append("|---|---|---|---:|" + "---:|" * len(PASSES) + "---:|---:|---:|---:|")
        for s in passes:
            f = s.get("figures") or {}
            cells = [fmt(get(f, "gpu_pass_ms", p, "median"), 3) for p in PASSES]
            md.append(
                f"| {fmt(s['title'])} | {s['state']} | {fmt(f.get('texture_backing'))} | {fmt(f.get('frames'))} | "
                + " | ".join(cells)
                + f" | {fmt(f.get('gpu_ms_per_frame_median_sum'), 3)} | {fmt(f.get('wall_ms_per_frame'))} | "
                f"{fmt(get(f, 'meshes_drawn', 'median'), 0)} / {fmt(get(f, 'meshes_drawn', 'max'), 0)} | "
                f"{fmt(get(f, 'meshes_culled', 'median'), 0)} |"
            )

    latency = [s for s in steps if s.get("kind") == "latency"]
    if latency:
        md.append("\n## 4. Real clock, 3840×2160, under a budget that evicts\n")
        md.append(
            "| run | state | backing | frames | frame ms median / mean / max | MB per path s | "
            "PSNR of mean MSE dB | evicted layers | dropped levels | frames over budget | peak resident MB | budget MB |"
        )
        md.append("|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
        for s in latency:
            f = s.get("figures") or {}
            fm = f.get("frame_ms") or {}
            peak = f.get("peak_resident_bytes")
            budget = f.get("memory_budget_bytes")
            md.append(
                f"| {fmt(s['title'])} | {s['state']} | {fmt(f.get('texture_backing'))} | {fmt(f.get('frames'))} | "
                f"{fmt(fm.get('median'))} / {fmt(fm.get('mean'))} / {fmt(fm.get('max'))} | "
                f"{fmt(f.get('mb_per_path_s'))} | {fmt(f.get('psnr_of_mean_mse_db'))} | {fmt(f.get('evicted_layers'))} | "
                f"{fmt(f.get('dropped_levels'))} | {fmt(f.get('frames_over_budget'))} | "
                f"{fmt(peak / 2**20 if peak is not None else None, 1)} | "
                f"{fmt(budget / 2**20 if budget is not None else None, 0)} |"
            )
        for s in steps:
            if s.get("kind") == "report" and s["state"] == "ok" and s.get("run_dir"):
                table = read_text(os.path.join(s["run_dir"], "table.md"))
                if table:
                    md.append("\n`citystream report` over these runs:\n")
                    md.append(table.strip())

    binds = [s for s in steps if s.get("kind") in ("device", "bind") and s.get("bind_cost")]
    if binds:
        md.append("\n## 5. bind_cost\n")
        md.append(
            "`vkQueueBindSparse` from submission until the device is idle, median of 7 "
            "(engine/benches/bind_cost.rs); bind / unbind ms per run.\n"
        )
        keyed = {}
        for s in binds:
            for r in s["bind_cost"]:
                keyed.setdefault((r.get("blocks"), r.get("pattern")), {})[s["id"]] = r
        ids = [s["id"] for s in binds]
        md.append("| blocks | pattern | entries | " + " | ".join(f"step {i} bind / unbind ms" for i in ids) + " | desktop model ms |")
        md.append("|---:|---|---:|" + "---:|" * len(ids) + "---:|")
        for (blocks, pattern), by_id in keyed.items():
            first = next(iter(by_id.values()))
            cells = [
                f"{fmt(by_id[i].get('bind_ms'), 3)} / {fmt(by_id[i].get('unbind_ms'), 3)}" if i in by_id else "-"
                for i in ids
            ]
            md.append(
                f"| {fmt(blocks)} | {fmt(pattern)} | {fmt(first.get('entries'))} | "
                + " | ".join(cells)
                + f" | {fmt(first.get('desktop_model_ms'), 3)} |"
            )

    failed = [s for s in steps if s.get("log_tail")]
    if failed:
        md.append("\n## Failures\n")
        for s in failed:
            md.append(f"**{s['id']}** ({fmt(s['title'])}), exit {fmt(s['rc'])}:\n")
            md.append("```")
            md.extend(l[:300] for l in s["log_tail"])
            md.append("```")

    md.append(
        "\nEvery step's log, summary.json, frames.csv and step 4's report are in gpu-check-runs.tar.gz "
        "(steps.tsv, logs/, runs/)."
    )
    with open(os.path.join(a.out, "gpu-check.md"), "w", encoding="utf-8") as f:
        f.write("\n".join(md) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
