#!/usr/bin/env bash
# README.md = docs/readme_head.md + docs/sections/*.md in order. Edit those, then run this.
set -euo pipefail
cd "$(dirname "$0")/.."
{ cat docs/readme_head.md; for f in docs/sections/[0-9]*.md; do cat "$f"; echo; done; } > README.md
