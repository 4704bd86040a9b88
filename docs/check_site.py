"""Open every page of a built documentation site in headless Chromium (Playwright driving Debian's ``chromium``, no
browser download) and fail on any console error, page error or request that leaves the machine (the site must work
offline: no web fonts, no CDN, no analytics); and check every link between its pages, anchors included
(:func:`broken_links`: read from the HTML, nothing fetched, so it runs offline too; links off the site are counted,
never followed).

    python docs/check_site.py docs/_build/html
"""

from __future__ import annotations

import shutil
import sys
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit


class _Page(HTMLParser):
    """The ids (and old-style ``<a name>``) a page defines and the links (href, src) it holds."""

    def __init__(self):
        super().__init__()
        self.ids: set[str] = set()
        self.links: list[str] = []

    def handle_starttag(self, tag, attrs):
        values = dict(attrs)
        self.ids.update(v for k in ("id", "name") if (v := values.get(k)) and (k == "id" or tag == "a"))
        self.links += [v for k in ("href", "src") if (v := values.get(k))]


def _pages(site: Path) -> list[Path]:
    return sorted(p for p in site.rglob("*.html") if "_static" not in p.relative_to(site).parts)  # (theme macros)


def broken_links(site: Path) -> tuple[dict[str, list[str]], int]:
    """Page (relative path) → its links to a file of the site that does not exist, or to an anchor its target page
    does not define; and the number of links off the site (http, https, mailto: counted, not followed)."""
    site = Path(site).resolve()
    parsed: dict[Path, _Page] = {}

    def page(path: Path) -> _Page:
        if path not in parsed:
            parsed[path] = _Page()
            parsed[path].feed(path.read_text(encoding="utf-8", errors="replace"))
        return parsed[path]

    found: dict[str, list[str]] = {}
    outside = 0
    for path in _pages(site):
        for link in page(path).links:
            parts = urlsplit(link)
            if parts.scheme or parts.netloc:
                outside += parts.scheme not in ("data", "javascript")
                continue
            target = (path.parent / unquote(parts.path)).resolve() if parts.path else path
            if target.is_dir():
                target = target / "index.html"
            why = None
            if not target.is_relative_to(site) or not target.exists():
                why = "no such file"
            elif parts.fragment and target.suffix == ".html" and unquote(parts.fragment) not in page(target).ids:
                why = f"no anchor #{parts.fragment} there"
            if why:
                found.setdefault(str(path.relative_to(site)), []).append(f"link {link}: {why}")
    return found, outside


def problems(site: Path, chromium: str) -> dict[str, list[str]]:
    """Page (relative path) → what went wrong loading it; empty when every page loads cleanly."""
    from playwright.sync_api import sync_playwright

    site = Path(site).resolve()  # a file:// address needs an absolute path
    pages = _pages(site)
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
    links, outside = broken_links(site)
    for page in sorted(set(found) | set(links)):
        print(f"{page}:", *found.get(page, []), *links.get(page, []), sep="\n  ", file=sys.stderr)
    print(f"{len(_pages(site))} pages opened in Chromium; {len(found)} with problems; links between pages checked: "
          f"{sum(map(len, links.values()))} broken ({outside} links off the site, not followed)")
    return 1 if found or links else 0


if __name__ == "__main__":
    sys.exit(main())
