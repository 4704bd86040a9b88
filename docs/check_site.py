"""Open every page of a built documentation site in headless Chromium (Playwright driving Debian's ``chromium``, no
browser download) and fail on any console error, page error or request that leaves the machine (the site must work
offline: no web fonts, no CDN, no analytics).

    python docs/check_site.py docs/_build/html
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path


def problems(site: Path, chromium: str) -> dict[str, list[str]]:
    """Page (relative path) → what went wrong loading it; empty when every page loads cleanly."""
    from playwright.sync_api import sync_playwright

    site = Path(site).resolve()  # a file:// address needs an absolute path
    pages = sorted(p for p in site.rglob("*.html") if "_static" not in p.relative_to(site).parts)  # (theme macros)
    found: dict[str, list[str]] = {}
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=chromium, headless=True, args=["--no-sandbox"])
        page = browser.new_page()
        seen: list[str] = []
        page.on("console", lambda m: seen.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
        page.on("pageerror", lambda e: seen.append(f"page error: {e}"))
        page.on("requestfailed", lambda r: seen.append(f"failed to load {r.url}"))
        page.on("request", lambda r: None if r.url.startswith(("file:", "data:", "blob:"))
                else seen.append(f"request off the machine: {r.url}"))
        for path in pages:
            seen.clear()
            page.goto(path.as_uri(), wait_until="load")
            if seen:
                found[str(path.relative_to(site))] = list(seen)
        browser.close()
    if not pages:
        found["(site)"] = [f"no HTML page under {site}"]
    return found


def main() -> int:
    site = Path(sys.argv[1] if len(sys.argv) > 1 else "docs/_build/html").resolve()
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        print("no Chromium: install Debian's chromium package (apt-get install chromium)", file=sys.stderr)
        return 2
    found = problems(site, chromium)
    for page, what in found.items():
        print(f"{page}:", *what, sep="\n  ", file=sys.stderr)
    count = sum(1 for p in site.rglob("*.html") if "_static" not in p.relative_to(site).parts)
    print(f"{count} pages opened in Chromium; {len(found)} with problems")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
