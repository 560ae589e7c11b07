#!/usr/bin/env python3
"""Every Rust path an embedding guide names resolves in the sources.

The host-facing guides (docs/EMBEDDING.md, docs/STRATEGIES.md) name API items in inline
code: `Type::method`, `Type::field`, `Enum::Variant`, `module::item` and
`citystream_engine::module::Item`. An item renamed, moved or turned into a trait method
leaves a sentence a host developer follows into a compile error; this check reads the
workspace's sources and fails naming every path that does not resolve. The migration
table's "before" column names what no longer exists on purpose, and is skipped.

Resolution reads the sources as text: an item is a `pub` (not `pub(crate)`) `struct`,
`enum`, `trait`, `type`, `fn`, `const`, `static` or `mod`, a `pub use` of it, or a constant
one of our macros defines; a type's members are the `pub` `fn`, `const` and `type` items of
its inherent `impl` blocks, the items of a trait's `impl … for` it or of the trait itself,
an enum's variants and a struct's `pub` fields; a module path is a file (`name.rs` or
`name/mod.rs`) of the crate.
Usage: doc-paths.py ROOT [DOC...]
"""

import re
import sys
from pathlib import Path

CRATES = {
    "citystream_engine": "engine/src",
    "citystream_streaming": "streaming/src",
    "citystream_dataset": "streaming/dataset/src",
    "citystream_cache": "cache/src",
}
# Paths into other crates (the standard library, ash, anyhow) are not ours to check.
EXTERNAL = {"std", "core", "alloc", "anyhow", "ash", "vk", "thiserror", "serde", "tokio"}
DEFAULT_DOCS = ["docs/EMBEDDING.md", "docs/STRATEGIES.md"]
# The example host the guide walks through defines types of its own.
EXAMPLES = ["engine/examples"]


def strip_comments(text):
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    return re.sub(r"//[^\n]*", "", text)


def block_after(text, start):
    """The text of the `{ … }` block opening at or after `start`."""
    open_at = text.find("{", start)
    if open_at < 0:
        return ""
    depth = 0
    for i in range(open_at, len(text)):
        if text[i] == "{":
            depth += 1
        elif text[i] == "}":
            depth -= 1
            if depth == 0:
                return text[open_at + 1 : i]
    return text[open_at + 1 :]


class Sources:
    def __init__(self, root):
        self.root = root
        self.files = {}
        for crate_dir in list(CRATES.values()) + EXAMPLES:
            for path in (root / crate_dir).rglob("*.rs"):
                self.files[path] = strip_comments(path.read_text(encoding="utf-8", errors="replace"))

    def defines(self, text, name):
        # Public to a host: `pub`, not `pub(crate)`.
        pattern = rf"\bpub\s+(?:(?:unsafe|async|const)\s+)*(?:struct|enum|trait|type|fn|const|static|mod|union)\s+{re.escape(name)}\b"
        if re.search(pattern, text):
            return True
        # Defined by a macro of ours: `shader!(NAME, …)`.
        if re.search(rf"\b\w+!\(\s*{re.escape(name)}\s*,", text):
            return True
        # Re-exported: `pub use …::name;` or within braces.
        return bool(re.search(rf"\bpub\s+use\b[^;]*\b{re.escape(name)}\b[^;]*;", text))

    def type_members(self, type_name, member):
        found_type = False
        for path, text in self.files.items():
            example = any(str(path).startswith(str(self.root / e)) for e in EXAMPLES)
            for kind in ("struct", "enum", "trait", "union"):
                for m in re.finditer(rf"\b{kind}\s+{re.escape(type_name)}\b", text):
                    found_type = True
                    body = block_after(text, m.end())
                    if kind == "trait" and re.search(rf"\b(?:fn|const|type)\s+{re.escape(member)}\b", body):
                        return True, True
                    if kind == "enum" and re.search(rf"(?:^|[,{{\s]){re.escape(member)}\b\s*[,({{=]?", body):
                        return True, True
                    if kind in ("struct", "union") and re.search(rf"\bpub\s+{re.escape(member)}\s*:", body):
                        return True, True
            if re.search(rf"\btype\s+{re.escape(type_name)}\b", text):
                found_type = True
            # impl [<…>] [Trait for] Type[<…>] {
            for m in re.finditer(r"\bimpl\b", text):
                head_end = text.find("{", m.end())
                if head_end < 0:
                    continue
                head = text[m.end() : head_end]
                if ";" in head:
                    continue
                self_type = head.split(" for ")[-1] if " for " in head else head
                self_type = re.sub(r"<[^<>]*(?:<[^<>]*>[^<>]*)*>", "", self_type)
                if re.search(rf"(?:^|[\s:]){re.escape(type_name)}\s*(?:where\b.*)?$", self_type.strip(), re.S) is None:
                    continue
                body = block_after(text, m.end())
                # An inherent item must be `pub`; a trait's items are as public as the trait.
                visibility = "" if " for " in head or example else r"pub\s+(?:(?:unsafe|async|const)\s+)*"
                if re.search(rf"\b{visibility}(?:fn|const|type)\s+{re.escape(member)}\b", body):
                    return True, True
        return found_type, False

    def module_file(self, crate_dir, modules):
        base = self.root / crate_dir
        candidates = [base.joinpath(*modules).with_suffix(".rs"), base.joinpath(*modules, "mod.rs")]
        if not modules:
            candidates = [base / "lib.rs"]
        for c in candidates:
            if c in self.files:
                return c
        return None

    def module_anywhere(self, name):
        return [p for p in self.files if p.stem == name or (p.name == "mod.rs" and p.parent.name == name)]


def paths_in(doc):
    """(line number, path) of each inline-code path outside code blocks and outside the
    migration table's "before" column."""
    in_code = False
    in_migration = False
    for number, line in enumerate(doc.read_text(encoding="utf-8").splitlines(), 1):
        if line.startswith("```"):
            in_code = not in_code
            continue
        if in_code:
            continue
        if line.startswith("## "):
            in_migration = line.lower().startswith("## migrating")
        text = line
        if in_migration and line.startswith("|"):
            cells = line.split("|")
            text = "|".join(cells[2:]) if len(cells) > 3 else ""
        for span in re.findall(r"`([^`]+)`", text):
            for path in expand(span):
                yield number, path


def expand(span):
    """The paths a code span names: `a::b::{C, D}` is two, arguments and types cut off."""
    span = re.sub(r"^\s*(?:unsafe\s*\{\s*|let\s+\w+\s*=\s*|use\s+)", "", span)
    m = re.match(r"[&\s]*((?:[A-Za-z_][A-Za-z0-9_]*::)+)(\{[^}]*\}|[A-Za-z_][A-Za-z0-9_]*)", span)
    if not m:
        return []
    prefix = m.group(1)
    tail = m.group(2)
    if tail.startswith("{"):
        items = [t.strip() for t in tail[1:-1].split(",")]
        return [prefix + t for t in items if re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", t)]
    return [prefix + tail]


def resolve(sources, path):
    """None when `path` resolves, else why not."""
    segments = path.split("::")
    if segments[0] in EXTERNAL:
        return None
    if segments[0] in CRATES:
        crate_dir = CRATES[segments[0]]
        rest = segments[1:]
        modules = []
        # Descend through module files while they exist.
        while rest and sources.module_file(crate_dir, modules + [rest[0]]) is not None:
            modules.append(rest.pop(0))
        if not rest:
            return None
        module = sources.module_file(crate_dir, modules)
        if module is None or not sources.defines(sources.files[module], rest[0]):
            return f"`{rest[0]}` is not defined or re-exported in {crate_dir}/{'/'.join(modules) or 'lib'}"
        if len(rest) == 1:
            return None
        return member_of(sources, rest[-2], rest[-1])
    first = segments[0]
    if first[0].islower():
        # `module::item`: a module of one of our crates.
        modules = sources.module_anywhere(first)
        if not modules:
            return f"no module `{first}` in the crates"
        if len(segments) == 2:
            if any(sources.defines(sources.files[m], segments[1]) for m in modules):
                return None
            return f"`{segments[1]}` is not defined in any module `{first}`"
        return member_of(sources, segments[-2], segments[-1])
    return member_of(sources, segments[-2], segments[-1])


def member_of(sources, type_name, member):
    found_type, found_member = sources.type_members(type_name, member)
    if found_member:
        return None
    if not found_type:
        return f"no type `{type_name}` in the crates"
    return f"`{type_name}` has no public method, associated item, variant or field `{member}`"


def main():
    root = Path(sys.argv[1] if len(sys.argv) > 1 else ".")
    docs = sys.argv[2:] or DEFAULT_DOCS
    sources = Sources(root)
    failures = []
    checked = 0
    for doc in docs:
        for number, path in paths_in(root / doc):
            checked += 1
            why = resolve(sources, path)
            if why:
                failures.append(f"{doc}:{number}: `{path}`: {why}")
    for failure in failures:
        print(failure, file=sys.stderr)
    print(f"doc paths: {checked} checked in {', '.join(docs)}, {len(failures)} not resolving")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
