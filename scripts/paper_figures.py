"""Print the numbers behind the GGNS paper's bar charts from its LaTeX source (how
conf/paper/ggns_iclr2023.yaml was read): per pgfplots axis, its caption, x tick labels, bar heights
and error-bar ends (low, high).

Usage: python scripts/paper_figures.py PAPER.tex
"""
from __future__ import annotations

import re
import sys


def main(path: str) -> None:
    text = open(path, encoding="utf-8").read()
    for axis in re.finditer(r"\\begin\{axis\}(.*?)\\end\{axis\}", text, re.S):
        body, after = axis.group(1), text[axis.end():axis.end() + 600]
        caption = re.search(r"\\caption\{(.*?)\}\n", after)
        ticks = re.search(r"xticklabels=\{(.*?)\},\n", body, re.S)
        bars = [float(y) for y in re.findall(r"rectangle \(axis cs:[-\d.]+,([-\deE.+]+)\)", body)]
        errors = [(float(a), float(b)) for a, b in
                  re.findall(r"\(axis cs:[-\d.]+,([-\deE.+]+)\)\n--\(axis cs:[-\d.]+,([-\deE.+]+)\)", body)]
        if not bars:
            continue
        print(f"line {text[:axis.start()].count(chr(10)) + 1}: {caption.group(1)[:60] if caption else '(no caption)'}")
        print("  ticks:", re.sub(r"\s+", " ", ticks.group(1)).strip() if ticks else "-")
        print("  bars: ", ", ".join(f"{v:.4g}" for v in bars))
        print("  error bars:", ", ".join(f"[{a:.4g}, {b:.4g}]" for a, b in errors[:len(bars)]))


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    main(sys.argv[1])
