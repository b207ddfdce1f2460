"""`snakemake --report report.html` for a tiny scene: the evaluation renders, the metrics table,
the training curve and (when the benchmark has made it) the Pareto plot are in the HTML.
That the pictures show in a browser is checked by hand: scripts/report_screenshots.py."""

from __future__ import annotations

import base64
import json
import re

import cv2
import numpy as np
import pytest

from tests.conftest import REPO


def report_results(html: str) -> dict:
    """The report's results (path -> name, mime type, data URI, ...) and categories."""
    results = json.loads(re.search(r"var results = (\{.*?\});\n", html, re.S).group(1))
    categories = json.loads(re.search(r"var categories = (\{.*?\});\n", html, re.S).group(1))
    return results, categories


def decode(data_uri: str) -> bytes:
    return base64.b64decode(data_uri.split("base64,", 1)[1])


@pytest.mark.workflow
def test_report_of_a_tiny_scene_holds_renders_metrics_curve_and_pareto_plot(workflow):
    from tests.test_batch import TINY_FULL

    workflow.write_scene("tiny", TINY_FULL)
    workflow.write_config({"scenes_dir": "config/scenes", "scenes": ["tiny"], "results_dir": "results",
                           "final_artifact": "eval"})
    workflow.run()
    workflow.run("--report", "report.html")
    results, categories = report_results((workflow.root / "report.html").read_text())
    eval_dir = workflow.root / "results" / "tiny" / "eval"
    renders = sorted(p.name for p in (eval_dir / "renders").glob("*.png"))
    assert renders and sorted(categories["tiny"]) == ["held-out renders", "metrics", "training curve"]
    assert sorted(r.rsplit("/", 1)[1] for r in categories["tiny"]["held-out renders"]) == renders
    for name in renders:
        entry = results[f"results/tiny/eval/renders/{name}"]
        assert entry["mime_type"] == "image/png" and "Held-out view" in entry["caption"]
        image = cv2.imdecode(np.frombuffer(decode(entry["data_uri"]), np.uint8), cv2.IMREAD_COLOR)
        assert image.shape == cv2.imread(str(eval_dir / "renders" / name)).shape  # the whole figure
    metrics = results["results/tiny/eval/metrics.html"]
    assert metrics["mime_type"] == "text/html" and "samples skipped in empty space" in decode(metrics["data_uri"]).decode()
    curve = results["results/tiny/eval/training_curve.svg"]
    assert curve["mime_type"] == "image/svg+xml" and b"<polyline" in decode(curve["data_uri"])
    pareto = REPO / "benchmarks" / "results" / "tradeoff.png"
    if pareto.is_file():
        assert categories["Speed and accuracy"]["Pareto plot"] == [str(pareto)]
        assert decode(results[str(pareto)]["data_uri"]) == pareto.read_bytes()
