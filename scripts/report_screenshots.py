"""Screenshots of a Snakemake report in headless Chromium, one per result, to check by eye that
the pictures show (the report is a single-page app: each shot opens a copy of it with a script
that selects one category and result, as a click would).

    snakemake --report report.html
    python scripts/report_screenshots.py report.html --out report_shots/     # needs `chromium`

Writes index.png (the landing page) and one PNG per result: <category>__<file>.png.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

SHOW = """<script>
setTimeout(function () {
  var path = %s, category = %s, subcategory = %s, entry = results[path];
  app.setView({navbarMode: "subcategory", category: category, subcategory: subcategory,
               content: entry.mime_type === "text/html" ? "html" : "img", contentPath: entry.data_uri,
               resultPath: path});
}, 300);
</script></body>"""


def result_paths(report: str) -> dict[str, tuple[str, str]]:
    """Result path -> (category, subcategory), read from the report's `var categories = {...};`."""
    match = re.search(r"var categories = (\{.*?\});\n", report, re.S)
    if not match:
        raise ValueError("no `var categories` in this file: is it a Snakemake 9 report?")
    return {path: (category, subcategory) for category, subs in json.loads(match.group(1)).items()
            for subcategory, paths in subs.items() for path in paths}


def shoot(chromium: str, html: Path, png: Path, size: str) -> None:
    subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    f"--window-size={size}", "--virtual-time-budget=5000", f"--screenshot={png}", html.as_uri()],
                   check=True, capture_output=True, timeout=120)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("report", type=Path)
    parser.add_argument("--out", type=Path, default=Path("report_shots"))
    parser.add_argument("--size", default="1400,1000", help="window width,height")
    args = parser.parse_args()
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        print("chromium not found (Debian: apt-get install chromium)", file=sys.stderr)
        return 1
    report = args.report.read_text()
    args.out.mkdir(parents=True, exist_ok=True)
    shoot(chromium, args.report.resolve(), args.out / "index.png", args.size)
    with tempfile.TemporaryDirectory() as tmp:
        for path, (category, subcategory) in result_paths(report).items():
            name = re.sub(r"[^A-Za-z0-9_.-]+", "_", f"{category}__{Path(path).name}")
            page = Path(tmp) / "report.html"
            script = SHOW % (json.dumps(path), json.dumps(category), json.dumps(subcategory))
            head, _, tail = report.rpartition("</body>")  # the last: the libraries hold one in a string
            page.write_text(head + script + tail)
            shoot(chromium, page, args.out / f"{Path(name).stem}.png", args.size)
            print(args.out / f"{Path(name).stem}.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
