"""The text table of a ``vlocnetpp bench`` report: per figure its value, target, whether it is met and the absolute
times behind it."""

from __future__ import annotations


def format_table(report: dict) -> str:
    """The report as a text table: figure, value, target, met, and the absolute times behind it."""
    from vlocnetpp_core.bench import SOAK_FIGURES  # the package imports this module first

    t = report["times_ms"]
    basis = {
        "cached_vs_recompute_speedup": f"recompute {t.get('paper_step_recompute', 0):.1f} ms "
        f"/ cached {t.get('paper_step_cached', 0):.1f} ms"
        f" at {report['paper_input_size'][0]}x{report['paper_input_size'][1]}",
        "mtl_step_over_resnet50": f"{report['paper_backend']}: torch step {t['paper_step_cached']:.1f} ms"
        + (f", onnx {t['paper_step_onnx']:.1f} ms" if "paper_step_onnx" in t else "")
        + (f", CUDA graph {t['paper_step_cuda_graph']:.2f} ms" if "paper_step_cuda_graph" in t else "")
        + (f", compiled {t['paper_step_compiled']:.2f} ms" if "paper_step_compiled" in t else "")
        + f" / ResNet-50 {t['resnet50_forward']:.1f} ms (compute {report['mtl_gmac_over_resnet50']:.2f}x)",
        "node_latency_over_step": (
            f"node {t['node_latency']:.1f} ms / bare {t['node_bare_step']:.1f} ms "
            f"({report['settings']['node_backend']}, "
            f"{report['settings']['node_transport']} DDS, "
            f"camera {report['camera_size'][0]}x{report['camera_size'][1]})"
        )
        if "node_latency" in t
        else "not measured",
        "lite_hz": f"{report['lite_backend']}: torch {t['lite_step_torch']:.1f} ms"
        + (f", onnx {t['lite_step_onnx']:.1f} ms" if "lite_step_onnx" in t else "")
        + f" at {report['lite_input_size'][0]}x{report['lite_input_size'][1]}",
        "converter_speed_over_png_decode": (
            f"decode {t['png_decode_frame']:.2f} ms / convert {t['converter_frame']:.2f} ms per frame; "
            f"CPU: decode threads {t['converter_cpu_decode_threads']:.2f}, main {t['converter_cpu_main_thread']:.2f} "
            f"-> {report['converter_speed_over_png_decode_idle_estimate']:.2f} on an idle 2-core machine"
        )
        if "converter_frame" in t
        else "not measured",
        "synth_fps": f"{t['synth_frame']:.1f} ms per frame",
        "train_nchw_over_nhwc": f"NCHW {t['train_step_nchw']:.0f} ms / channels-last "
        f"{t['train_step_nhwc']:.0f} ms per step",
        "peak_rss_mb": f"now {report['node_rss_mb']:.0f} MiB" if "node_rss_mb" in report else "not measured",
        "paper_step_ms": f"{report['machine']['device']}",
        "node_refined_hz": _refinement_basis(report),
        **dict.fromkeys(SOAK_FIGURES, _soak_basis(report)),
    }
    rows = [("figure", "value", "target", "met", "absolute")]
    for name, entry in report["targets"].items():
        value = "-" if entry["value"] is None else f"{entry['value']:.2f}"
        target = "-" if entry["target"] is None else f"{entry['compare']} {entry['target']:g}"
        met = {True: "yes", False: "NO", None: "-"}[entry["met"]]
        rows.append((name, value, target, met, basis[name]))
    widths = [max(len(r[i]) for r in rows) for i in range(4)]
    lines = ["  ".join(r[i].ljust(widths[i]) for i in range(4)) + "  " + r[4] for r in rows]
    m = report["machine"]
    lines.append(
        f"\n{m['device']}, {m['cpus']} CPUs, torch {m['torch']} ({m['torch_threads']} threads), "
        f"onnxruntime {m['onnxruntime'] or 'not installed'}; "
        f"load average {m['load_average_start']} -> {m['load_average_end']}"
    )
    lines += [f"note: {n}" for n in report["notes"]]
    return "\n".join(lines)


def _refinement_basis(report: dict) -> str:
    """The refinement's absolute times: per-frame cost over the network's step, and every 2nd frame."""
    t = report["times_ms"]
    if "refine_step_every1" not in t:
        return "not measured"
    text = (
        f"step: network {t['refine_step_none']:.1f} ms, refining every frame {t['refine_step_every1']:.1f} ms "
        f"(+{t['refine_step_every1'] - t['refine_step_none']:.1f} ms, "
        f"{100 * report['refine_share_every1']:.0f} % refined), "
        f"every 2nd {t['refine_step_every2']:.1f} ms"
    )
    if "node_refined_latency_every1" in t:
        share = report.get("node_refine_share_every1")
        text += (
            (f"; node: {100 * share:.0f} % of its poses refined" if share is not None else "")
            + f"; node lockstep {1000 / t['node_refined_latency_every1']:.1f} Hz, every 2nd frame "
            f"{1000 / t['node_refined_stream_every2']:.1f} Hz (lockstep {1000 / t['node_refined_latency_every2']:.1f})"
        )
    return text


def _soak_basis(report: dict) -> str:
    """The soak's counts, latency median, RSS and plot (or why it did not run)."""
    soak = report.get("soak")
    if soak is None:
        return "not run (bench setting soak_minutes: 0)" if not report["settings"]["soak_minutes"] else "not measured"
    return (
        f"{soak['minutes']:g} min: {soak['answered']} of {soak['good_frames_sent']} good frames answered, "
        f"{soak['bad_messages_sent']} bad messages; p50 {soak['latency_ms_p50']:.0f} ms; "
        f"RSS {soak['rss_mb_start']:.0f} MiB after 1 min; plot {soak['plot']}"
    )
