#!/usr/bin/env python3
"""Check every relative link (and #anchor) in the repository's Markdown files resolves."""
import os, re, subprocess, sys
root = sys.argv[1] if len(sys.argv) > 1 else "."
os.chdir(root)
files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "*.md"],
                       capture_output=True, text=True, check=True).stdout.split()
def slug(h):
    h = h.strip().lower()
    h = re.sub(r"[`*_]", "", h)
    h = re.sub(r"[^\w\- ]", "", h)
    return h.replace(" ", "-")
def anchors(path):
    out, fence = set(), False
    for line in open(path, encoding="utf-8"):
        if line.startswith("```"): fence = not fence
        if not fence and line.startswith("#"):
            out.add(slug(line.lstrip("#")))
    return out
bad = 0
link = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
for f in files:
    text = open(f, encoding="utf-8").read()
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    for target in link.findall(text):
        if re.match(r"^[a-z]+:", target):
            continue
        path, _, frag = target.partition("#")
        full = os.path.normpath(os.path.join(os.path.dirname(f), path)) if path else f
        if not os.path.exists(full):
            print(f"{f}: missing {target}"); bad += 1; continue
        if frag and full.endswith(".md") and frag not in anchors(full):
            print(f"{f}: no anchor #{frag} in {full}"); bad += 1
print(f"{len(files)} files checked, {bad} bad links")
sys.exit(1 if bad else 0)
