"""Lists import loops between the modules of each crate (python3 tools/scripts/module-loops.py .):
modules are files; an edge is a `use crate::`, `super::` or `self::` path outside comments and
unit tests. Prints every loop, of any length, and the two-module ones; exits 1 if there is one."""
import os, re, sys, glob, itertools
root = sys.argv[1]
crates = [os.path.dirname(p) for p in glob.glob(f"{root}/**/Cargo.toml", recursive=True) if "/target/" not in p]
def files_of(src):
    out = {}
    for p in glob.glob(f"{src}/**/*.rs", recursive=True):
        rel = os.path.relpath(p, src)[:-3].split(os.sep)
        if rel[-1] == "mod": rel = rel[:-1]
        if rel in (["lib"], ["main"]): rel = []
        out[tuple(rel)] = p
    return out
total = loops = 0
for c in sorted(crates):
    for src in [f"{c}/src"]:
        if not os.path.isdir(src): continue
        mods = files_of(src)
        edges = {m: set() for m in mods}
        for m, p in mods.items():
            text = "\n".join(l for l in open(p).read().splitlines() if not l.lstrip().startswith("//"))
            # drop #[cfg(test)] mod tests { ... } blocks roughly: cut at "#[cfg(test)]\nmod tests"
            text = re.split(r"#\[cfg\(test\)\]\s*mod tests", text)[0]
            for path in re.findall(r"\b((?:crate|super|self)(?:::\w+)+)", text):
                parts = path.split("::")
                if parts[0] == "crate": base, rest = [], parts[1:]
                else:
                    base = list(m) if (os.path.basename(p) in ("mod.rs", "lib.rs", "main.rs")) else list(m[:-1])
                    if parts[0] == "self": base = list(m)
                    rest = parts[1:] if parts[0] == "self" else parts[1:]
                    if parts[0] == "super":
                        k = 0
                        while k < len(parts) and parts[k] == "super":
                            k += 1
                        base = list(m)[: len(m) - k]
                        rest = parts[k:]
                target = tuple(base)
                for r in rest:
                    if tuple(list(target) + [r]) in mods: target = tuple(list(target) + [r])
                    else: break
                if target != m and target in mods: edges[m].add(target)
        # Any loop, of any length: strongly connected components of more than one module.
        index, low, stack, on, sccs, counter = {}, {}, [], set(), [], [0]
        def strong(v):
            index[v] = low[v] = counter[0]; counter[0] += 1; stack.append(v); on.add(v)
            for w in edges[v]:
                if w not in index: strong(w); low[v] = min(low[v], low[w])
                elif w in on: low[v] = min(low[v], index[w])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop(); on.discard(w); comp.append(w)
                    if w == v: break
                if len(comp) > 1: sccs.append(comp)
        for v in mods:
            if v not in index: strong(v)
        loops += len(sccs)
        for comp in sccs:
            print(f"{os.path.relpath(src, root)}: loop among {sorted('::'.join(x) or 'crate' for x in comp)}")
        for a, b in itertools.combinations(mods, 2):
            if b in edges[a] and a in edges[b]:
                # parent <-> child via super is Rust's normal shape only if reported separately
                kind = "parent/child" if (a == b[:len(a)] or b == a[:len(b)]) else "siblings"
                print(f"{os.path.relpath(src, root)}: {'::'.join(a) or 'crate'} <-> {'::'.join(b) or 'crate'} ({kind})")
                total += 1
print(f"{total} two-module loops, {loops} loops in all")
sys.exit(1 if loops else 0)
