"""A Mitsuba XML file as a tree of elements: read with expat (line numbers
for every element; DOCTYPE and entity declarations refused, so no entity
expansion and no external entities), `<include>`s spliced in, `$name`s
substituted from the `<default>`s, ids recorded for `<ref>`s; and the
importer's report and the files a scene names, inside its root.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from xml.parsers import expat

from ...errors import SceneError
from .. import ReportEntry

MAX_XML_BYTES = 32 * 1024 * 1024  # one XML file
MAX_ELEMENTS = 200_000  # elements over the scene and all its includes
MAX_NESTING = 32  # elements inside elements, per file
MAX_INCLUDE_DEPTH = 8  # includes inside includes
MAX_REF_DEPTH = 16  # objects inside objects (bsdf in twosided in mask ...), refs followed


class _Node:
    __slots__ = ("tag", "attrs", "file", "line", "children")

    def __init__(self, tag: str, attrs: dict, file: str, line: int):
        self.tag, self.attrs, self.file, self.line = tag, attrs, file, line
        self.children: list[_Node] = []

    @property
    def loc(self) -> str:
        return f"{self.file}:{self.line}"

    def describe(self) -> str:
        return " ".join([self.tag] + [f'{k}="{self.attrs[k]}"' for k in ("type", "name", "id")
                                      if k in self.attrs])



def _parse_xml(path: Path, rel: str) -> _Node:
    """The element tree of one XML file, refusing what could attack the reader."""
    try:
        size = path.stat().st_size
        if size > MAX_XML_BYTES:
            raise SceneError(f"the XML file is {size} bytes; at most {MAX_XML_BYTES}", f"{rel}:1")
        data = path.read_bytes()
    except OSError as exc:
        raise SceneError(f"cannot read {rel}: {exc.strerror}", rel) from None
    parser = expat.ParserCreate()
    parser.SetParamEntityParsing(expat.XML_PARAM_ENTITY_PARSING_NEVER)
    stack: list[_Node] = []
    top: list[_Node] = []
    count = [0]

    def refuse(what: str):
        def handler(*_args):
            raise SceneError(f"{what} are refused (entity expansion and external entities "
                             "could exhaust or leak the service)", f"{rel}:{parser.CurrentLineNumber}")
        return handler

    def start(tag, attrs):
        count[0] += 1
        if count[0] > MAX_ELEMENTS:
            raise SceneError(f"more than {MAX_ELEMENTS} elements", f"{rel}:{parser.CurrentLineNumber}")
        if len(stack) >= MAX_NESTING:
            raise SceneError(f"elements nest more than {MAX_NESTING} deep",
                             f"{rel}:{parser.CurrentLineNumber}")
        node = _Node(tag, attrs, rel, parser.CurrentLineNumber)
        (stack[-1].children if stack else top).append(node)
        stack.append(node)

    parser.StartDoctypeDeclHandler = refuse("DOCTYPE declarations")
    parser.EntityDeclHandler = refuse("entity declarations")
    parser.ExternalEntityRefHandler = refuse("external entities")
    parser.StartElementHandler = start
    parser.EndElementHandler = lambda tag: stack.pop()
    try:
        parser.Parse(data, True)
    except expat.ExpatError as exc:
        raise SceneError(f"not well-formed XML: {expat.ErrorString(exc.code)}",
                         f"{rel}:{exc.lineno}") from None
    if not top:
        raise SceneError("the file has no root element", f"{rel}:1")
    return top[0]


class XmlTree:
    """The importer's tree, report and files (a base of scene._Importer,
    whose __init__ sets the state these methods share)."""

    # -- reporting and locations ---------------------------------------------------------
    def note(self, node: _Node, action: str) -> None:
        element = node.describe()
        if "id" not in node.attrs:  # name the enclosing object that has one, for context
            owner = next((n for n in reversed(self.map_stack) if n is not node and "id" in n.attrs),
                         None)
            if owner is not None:
                element += f" (in {owner.describe()})"
        self.report.append(ReportEntry(element, node.file, node.line, action))

    def rel(self, path: Path) -> str:
        return path.relative_to(self.root).as_posix()

    def anonymous(self, kind: str, node: _Node) -> str:
        """The name of an object without an id (``bsdf@scene.xml:12``): its
        file relative to the main file's folder, not to the root, so that a
        folder uploaded as it is or under its name is one scene (one hash)."""
        file = Path(os.path.relpath(self.root / node.file, self.main.parent)).as_posix()
        return f"{kind}@{file}:{node.line}"

    def find_file(self, name: str, node: _Node, what: str) -> Path:
        """A file a scene names: relative to the naming file's folder, or else
        to the main scene's; inside the root either way."""
        name = name.replace("\\", "/")
        if not name:
            raise SceneError(f"{what}: empty file name", node.loc)
        if name.startswith("/") or re.match(r"^[A-Za-z]:", name):
            raise SceneError(f"{what} '{name}' is an absolute path; a scene names its files "
                             "relative to its folder", node.loc)
        bases = [(self.root / node.file).parent, self.main.parent]
        for base in dict.fromkeys(bases):
            candidate = (base / name).resolve()
            if not candidate.is_relative_to(self.root):
                raise SceneError(f"{what} '{name}' lies outside the scene's folder", node.loc)
            if candidate.is_file():
                return candidate
        hint = ""
        parent = (bases[0] / name).parent
        if parent.is_dir():
            lower = Path(name).name.lower()
            near = [p.name for p in parent.iterdir() if p.name.lower() == lower]
            if near:
                hint = f" (there is '{near[0]}': names are case-sensitive)"
        raise SceneError(f"{what} '{name}' not found{hint}", node.loc)

    # -- includes, defaults, substitution --------------------------------------------------
    def substitute(self, text: str) -> str:
        return re.sub(r"\$([A-Za-z_][A-Za-z0-9_]*)",
                      lambda m: self.params.get(m.group(1), m.group(0)), text)

    def expand(self, node: _Node) -> list[_Node]:
        self.elements += 1
        if self.elements > MAX_ELEMENTS:
            raise SceneError(f"more than {MAX_ELEMENTS} elements with the includes", node.loc)
        attrs = {k: self.substitute(v) for k, v in node.attrs.items()}
        if node.tag == "default":
            if "name" not in attrs or "value" not in attrs:
                raise SceneError("<default> needs a name and a value", node.loc)
            self.params.setdefault(attrs["name"], attrs["value"])
            return []
        if node.tag == "include":
            if "filename" not in attrs:
                raise SceneError("<include> needs a filename", node.loc)
            path = self.find_file(attrs["filename"], node, "included file")
            if path in self.include_stack or path == self.main:
                chain = " -> ".join(self.rel(p) for p in [self.main, *self.include_stack, path])
                raise SceneError(f"include cycle: {chain}", node.loc)
            if len(self.include_stack) >= MAX_INCLUDE_DEPTH:
                raise SceneError(f"includes nest more than {MAX_INCLUDE_DEPTH} deep", node.loc)
            sub = _parse_xml(path, self.rel(path))
            if sub.tag != "scene":
                raise SceneError(f"an included file's root must be <scene>, not <{sub.tag}>",
                                 sub.loc)
            self.include_stack.append(path)
            out = [n for ch in sub.children for n in self.expand(ch)]
            self.include_stack.pop()
            return out
        new = _Node(node.tag, attrs, node.file, node.line)
        new.children = [n for ch in node.children for n in self.expand(ch)]
        if "id" in attrs and node.tag != "ref":
            if attrs["id"] in self.ids:
                raise SceneError(f"id '{attrs['id']}' is defined twice (first at "
                                 f"{self.ids[attrs['id']].loc})", node.loc)
            self.ids[attrs["id"]] = new
        return [new]

    def deref(self, ref: _Node) -> _Node:
        rid = ref.attrs.get("id")
        if rid not in self.ids:
            raise SceneError(f"<ref> to an unknown id '{rid}'", ref.loc)
        return self.ids[rid]

    def enter(self, node: _Node) -> None:
        """Guard against objects that contain themselves (by refs) or nest too deep."""
        if any(n is node for n in self.map_stack):
            chain = " -> ".join(n.describe() for n in [*self.map_stack, node])
            raise SceneError(f"reference cycle: {chain}", node.loc)
        if len(self.map_stack) >= MAX_REF_DEPTH:
            raise SceneError(f"objects nest (through refs) more than {MAX_REF_DEPTH} deep",
                             node.loc)
        self.map_stack.append(node)
