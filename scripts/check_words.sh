#!/usr/bin/env bash
# The product speaks of itself: docs, help texts, doc comments, Cargo
# descriptions and anything a tool writes describe the software as it is,
# not how it was developed. Fails on development-history words in tracked
# files; test files may name the regression they guard, and a playground
# or ONNX Runtime "session" is a product word.
set -euo pipefail
cd "$(dirname "$0")/.."
ordinals='first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|twelfth|thirteenth|fourteenth|fifteenth|sixteenth|seventeenth|eighteenth|nineteenth|twentieth|twenty-[a-z]+|thirtieth'
pattern="\\b(${ordinals}|this|last|previous|next|earlier|later)[- ]sessions?\\b|\\bthe filer\\b|\\bissues? [0-9]+\\b|\\bissue[0-9]+_"
if git grep -nIiE "$pattern" -- README.md docs crates tools benchmarks benches scripts fixtures Makefile Cargo.toml models_manifest \
     ':!*/tests/*' ':!tests/*' ':!scripts/check_words.sh'; then
  echo "error: the lines above speak of how the project was developed; say what the software does now (history belongs in git log)" >&2
  exit 1
fi
echo "words check: no development history in the product's text"
