"""Every relative Markdown link in the README, ``docs/`` (history included), ``bench/README.md``
and ``training/configs/README.md`` resolves to a file or folder in the repository."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def _pages() -> list[Path]:
    pages = [REPO / "README.md", REPO / "bench" / "README.md", REPO / "training" / "configs" / "README.md"]
    return [p for p in pages if p.is_file()] + sorted((REPO / "docs").rglob("*.md"))


def test_relative_links_resolve() -> None:
    broken = []
    for page in _pages():
        for n, line in enumerate(page.read_text().splitlines(), 1):
            for target in LINK.findall(line):
                if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
                    continue  # URLs and in-page anchors
                if not (page.parent / target.split("#", 1)[0]).exists():
                    broken.append(f"{page.relative_to(REPO)}:{n}: {target}")
    assert not broken, "broken links:\n" + "\n".join(broken)
