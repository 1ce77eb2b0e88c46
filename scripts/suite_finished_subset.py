#!/usr/bin/env python3
# Usage: suite_finished_subset.py SUITE.json OUT_DIR DEST.json (then dm-eval --suite DEST.json --out OUT_DIR: all cache hits).
# Keeps the scenes and variants of benchmarks/suite.json whose runs all finished in OUT.
import json, os, sys
suite, out, dest = sys.argv[1:4]
s = json.load(open(suite))
def sid(sc): return f"{sc['preset']}-s{sc['seed']}-{sc['action']}"
done = lambda sc, v: os.path.isfile(f"{out}/runs/{sid(sc)}/{v['name']}/result.json")
scenes = [sc for sc in s['scenes'] if any(done(sc, v) for v in s['variants'])]
s['variants'] = [v for v in s['variants'] if all(done(sc, v) for sc in scenes)]
s['scenes'] = scenes
json.dump(s, open(dest, 'w'), indent=2)
print([sid(sc) for sc in scenes], [v['name'] for v in s['variants']])
