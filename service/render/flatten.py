"""Flatten an untrusted Mitsuba 3 scene into one self-contained XML document.

Mitsuba resolves `<default>`, `$name` and `<include>` itself, and its resolver falls back to the
process's working directory and its own install folder. A check that reads the XML with
different rules than Mitsuba can be walked around (docs/security.md). So we do that resolution here, with
Mitsuba's rules, and hand Mitsuba the result: one document with nothing left to substitute, no
`<include>`, and every file reference an absolute path we checked to lie inside the bundle root.

Mitsuba's rules, as read in mitsuba3 `src/core/parser.cpp` (3.9, `substitute_parameters`,
`parse_xml_node`, `parse_file_impl`):
- parameters: the caller's (`-D name=value`) come first; a `<default name value>` adds one only
  when no parameter of that name exists yet, so the caller's value and the *first* default win.
  The list is shared by every included file, in document order: the including file's defaults
  reach into its includes, and an include's defaults stay for what follows it.
- substitution runs on every attribute of every element (names, types, ids, filenames, the
  `<default>` and `<include>` tags' own attributes), when the parser reaches that element: keys
  longest first, a plain search for `$key` (so `$ab` with parameter `a` becomes value+"b"), a
  `\\$` is skipped and unescaped at the end; any `$` left is "undefined parameter".
- `<include filename>` resolves against the including file's folder, then the folders of the
  files that included it, then the resolver (for us: the entry scene's folder). An included
  `<scene>` contributes its objects (its plain properties are dropped); any other root becomes one
  object named by the include's `name`. Depth is capped (`max_include_depth`, 15).
- plugin files (`filename` of bitmap, ply, obj, serialized, envmap, gridvolume, measured, ...)
  resolve through the file resolver only: the entry scene's folder, never the including file's.

What names a file (checked, then rewritten to an absolute path inside the root):
- every `filename` attribute (`<include>`, `<spectrum filename>`) and every `<string>` whose
  property name is in FILE_PROPERTIES (every Mitsuba 3.9 plugin reads files through `filename`);
- any other `<string>` value that is absolute (`/`, `~`, `C:`), has a `..` component, or names an
  existing path relative to the scene folder or the process's working directory: those could
  reach a file through a plugin we do not know, so they get the same rules. Other strings
  (`<string name="mode" value="rgb"/>`) pass unchanged.
Files must exist, be regular files, and stay inside the root after following symlinks. Error
messages name the offending value as written, never a server path.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from xml.etree.ElementTree import Element, ParseError, TreeBuilder
from xml.sax.saxutils import escape

import defusedxml
from defusedxml.ElementTree import DefusedXMLParser

MAX_INCLUDE_DEPTH = 15  # Mitsuba's ParserConfig.max_include_depth
MAX_XML_FILES = 1024  # XML files read per scene (a fan-out of includes is exponential otherwise)
MAX_VALUE_CHARS = 65_536  # one attribute after substitution (nested defaults can double per level)
MAX_DOCUMENT_CHARS = 256 * 1024 * 1024
# Elements nested in one another, includes counted: real scenes nest about ten deep; the walk
# below and Mitsuba's own parser recurse once per level, so thousands would exhaust the stack.
MAX_ELEMENT_DEPTH = 100
FILE_PROPERTIES = frozenset({"filename"})
# Plain properties: dropped when they sit directly under an included <scene> (Mitsuba copies only
# the included scene's objects into the parent).
PROPERTY_TAGS = frozenset(
    {"float", "integer", "boolean", "string", "rgb", "spectrum", "vector", "point", "transform", "ref"}
)
_WORD = re.compile(r"^[A-Za-z0-9_]+$")  # parameter names and plugin types
_NAME_TAIL = re.compile(r"[A-Za-z0-9_]*")
_DRIVE = re.compile(r"^[A-Za-z]:")
_ATTRIBUTE_ESCAPES = {'"': "&quot;", "\n": "&#10;", "\r": "&#13;", "\t": "&#9;"}


class FlattenError(ValueError):
    """The scene breaks a rule; the message names the file and the value at fault."""


class MissingFile(FlattenError):
    """A file the scene names does not exist (in the bundle): `path` is where it was looked for
    first, so a local render can name it ("file not found: …") instead of speaking of a bundle."""

    def __init__(self, where: str, reference: str, path: Path) -> None:
        super().__init__(f"{where}: {reference!r} is not in the bundle")
        self.where, self.path = where, path


@dataclass(frozen=True)
class FlatScene:
    """One document Mitsuba can parse with no parameters, and what went into it."""

    document: str
    files: tuple[Path, ...]  # every file read or referenced (real paths inside the root)
    defaults: dict[str, str]  # `<default>` names in declaration order → their declared value
    used: frozenset[str]  # parameter names substituted somewhere
    origins: tuple[tuple[str, int], ...] = field(repr=False)  # (file, line) of each document line

    def declares(self, name: str) -> bool:
        """Whether the scene has a parameter `name` (a `<default>` or a `$name` in use)."""
        return name in self.defaults or name in self.used

    def locate(self, line: int) -> str:
        """`file.xml:line` in the bundle for a 1-based line of `document`."""
        if 1 <= line <= len(self.origins):
            label, source_line = self.origins[line - 1]
            return f"{label}:{source_line}"
        return f"line {line}"


@dataclass
class _Parameter:
    key: str  # "$name"
    value: str


def parse_param_pairs(pairs: list[str] | tuple[str, ...]) -> dict[str, str]:
    """`["NAME=VALUE", ...]` (the CLI's `--param`) as a dict; later pairs win."""
    params: dict[str, str] = {}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        if not sep:
            raise FlattenError(f"--param {pair!r}: expected NAME=VALUE")
        params[name.strip()] = value
    return params


def flatten_scene(
    xml_path: str | Path,
    *,
    root: str | Path,
    params: dict[str, str] | None = None,
    optional_params: dict[str, str] | None = None,
) -> FlatScene:
    """Resolve defaults, `$` and includes of `xml_path` with Mitsuba's rules, inside `root`.

    `params` are the user's (`--param`, API `"params"`): a name the scene neither declares nor
    uses is an error listing its `<default>` names. `optional_params` are the renderer's own
    (`frame`, `width`, `height`): applied where the scene uses them, ignored otherwise. Both
    override the scene's defaults and obey the same path rules as anything in the file.
    """
    flattener = _Flattener(Path(root), Path(xml_path), {**(optional_params or {}), **(params or {})})
    flat = flattener.run()
    unknown = sorted(name for name in (params or {}) if not flat.declares(name))
    if unknown:
        declared = ", ".join(flat.defaults) or "none"
        raise FlattenError(
            f"unknown scene parameter{'s' if len(unknown) > 1 else ''} {', '.join(unknown)}; "
            f"the scene's <default> parameters: {declared}"
        )
    return flat


class _Flattener:
    def __init__(self, root: Path, entry: Path, params: dict[str, str]) -> None:
        self.root = Path(os.path.realpath(root))
        self.entry = Path(os.path.realpath(entry))
        if not _inside(self.entry, self.root):
            raise FlattenError(f"{entry.name}: the scene file is not inside the bundle")
        self.base = self.entry.parent  # Mitsuba's resolver path for plugin files
        self.params: list[_Parameter] = []
        for name, value in params.items():
            if not isinstance(name, str) or not _WORD.match(name):
                raise FlattenError(f"parameter name {name!r}: use letters, digits and '_'")
            if not isinstance(value, str) or "\x00" in value or len(value) > MAX_VALUE_CHARS:
                raise FlattenError(f"parameter {name}: the value must be a string without NUL, at most {MAX_VALUE_CHARS} characters")
            self.params.append(_Parameter("$" + name, value))
        self.params.sort(key=lambda p: -len(p.key))  # stable: ties keep the caller's order
        self.defaults: dict[str, str] = {}
        self.used: set[str] = set()
        self.files: list[Path] = []
        self.lines: list[str] = []
        self.origins: list[tuple[str, int]] = []
        self.chars = 0
        self.xml_files_read = 0
        self.entry_major = 3

    # -- driver ---------------------------------------------------------------------------------

    def run(self) -> FlatScene:
        root_element = self._read(self.entry)
        label = self._label(self.entry)
        if root_element.tag != "scene":
            raise FlattenError(f"{label}: root element is <{root_element.tag}>, expected <scene>")
        self.entry_major = self._version(root_element, label)
        self._object(root_element, [self.entry], depth=0, level=0)
        return FlatScene(
            document="\n".join(self.lines) + "\n",
            files=tuple(dict.fromkeys(self.files)),
            defaults=dict(self.defaults),
            used=frozenset(self.used),
            origins=tuple(self.origins),
        )

    def _label(self, path: Path) -> str:
        return path.relative_to(self.root).as_posix()

    def _read(self, path: Path) -> Element:
        self.xml_files_read += 1
        if self.xml_files_read > MAX_XML_FILES:
            raise FlattenError(f"{self._label(path)}: the scene reads more than {MAX_XML_FILES} XML files")
        self.files.append(path)
        return _parse_xml(path, self._label(path))

    def _version(self, element: Element, label: str) -> int:
        version = element.get("version")
        if version is None:
            raise FlattenError(f"{label}: missing version attribute in root element <{element.tag}>")
        major = version.strip().split(".")[0]
        if not major.isdigit():
            raise FlattenError(f"{label}: invalid version number {version!r}")
        return int(major)

    # -- elements -------------------------------------------------------------------------------

    def _object(self, element: Element, stack: list[Path], depth: int, level: int,
                name: str | None = None, included_root: bool = False) -> None:
        """Emit `element` (substituted, checked) and its children at `level` of indentation."""
        where = f"{self._label(stack[-1])}:{element.line}"
        if level >= MAX_ELEMENT_DEPTH:  # one file is capped while parsed; this counts includes too
            raise FlattenError(f"{where}: elements nested deeper than {MAX_ELEMENT_DEPTH}")
        attributes = {key: self._substitute(value, where) for key, value in element.attrib.items()}
        tag = element.tag
        if tag == "default":
            self._default(attributes, where)
            return
        if tag == "include":
            self._include(attributes, stack, depth, level, where)
            return
        if tag == "path":
            raise FlattenError(f"{where}: <path> is not supported; name files relative to the scene file")
        if included_root:
            # An included non-scene root: the include names it; `version` belongs to the file.
            attributes.pop("version", None)
            attributes.pop("name", None)
            if name:
                attributes["name"] = name
        self._check_files(tag, attributes, where)
        children = [child for child in element if isinstance(child.tag, str)]
        opening = len(self.lines)
        self._emit(level, f"<{tag}{_attributes(attributes)}>", stack[-1], element.line)
        for child in children:
            self._object(child, stack, depth, level + 1)
        if len(self.lines) == opening + 1:  # nothing inside survived: write it self-closing
            self.lines[opening] = self.lines[opening][:-1] + "/>"
        else:
            self._emit(level, f"</{tag}>", stack[-1], element.line)

    def _default(self, attributes: dict[str, str], where: str) -> None:
        name, value = attributes.get("name"), attributes.get("value")
        if not name or value is None:
            raise FlattenError(f"{where}: <default> needs a non-empty name and a value")
        self.defaults.setdefault(name, value)
        key = "$" + name
        if any(p.key == key for p in self.params):
            return  # the caller's value or an earlier default wins
        # Mitsuba inserts before the first strictly shorter key: after the equally long ones.
        position = next((i for i, p in enumerate(self.params) if len(key) > len(p.key)), len(self.params))
        self.params.insert(position, _Parameter(key, value))

    def _include(self, attributes: dict[str, str], stack: list[Path], depth: int, level: int, where: str) -> None:
        reference = attributes.get("filename")
        if not reference:
            raise FlattenError(f"{where}: <include> needs a filename")
        if depth + 1 >= MAX_INCLUDE_DEPTH:
            raise FlattenError(f"{where}: includes nested deeper than {MAX_INCLUDE_DEPTH}")
        # The including file's folder first, then the folders of the files that included it,
        # then the resolver's (the entry scene's folder) — as Mitsuba clones and prepends.
        folders = list(dict.fromkeys([p.parent for p in reversed(stack)] + [self.base]))
        path = self._resolve(reference, where, folders)
        if path in stack:
            chain = " -> ".join(self._label(p) for p in stack + [path])
            raise FlattenError(f"{where}: include cycle {chain}")
        element = self._read(path)
        label = self._label(path)
        major = self._version(element, label)
        # Mitsuba upgrades pre-2.0 property names per file; inlined, the entry's version rules.
        if (major < 2) != (self.entry_major < 2):
            raise FlattenError(f"{label}: version {element.get('version')} cannot be mixed with the including scene's")
        if element.tag == "scene":
            # Substitution still runs on the included root's attributes (it may use `$`).
            for value in element.attrib.values():
                self._substitute(value, f"{label}:{element.line}")
            for child in element:
                if isinstance(child.tag, str) and child.tag not in PROPERTY_TAGS:
                    self._object(child, stack + [path], depth + 1, level)
        else:
            self._object(element, stack + [path], depth + 1, level, name=attributes.get("name"), included_root=True)

    # -- values ---------------------------------------------------------------------------------

    def _substitute(self, value: str, where: str) -> str:
        if "$" not in value:
            return value
        for parameter in self.params:
            position = value.find(parameter.key)
            while position != -1:
                if position > 0 and value[position - 1] == "\\":
                    position += len(parameter.key)
                else:
                    value = value[:position] + parameter.value + value[position + len(parameter.key):]
                    self.used.add(parameter.key[1:])
                    position += len(parameter.value)
                    if len(value) > MAX_VALUE_CHARS:
                        raise FlattenError(f"{where}: an attribute grows beyond {MAX_VALUE_CHARS} characters through $ substitution")
                position = value.find(parameter.key, position)
        position = value.find("$")
        while position != -1:
            if position == 0 or value[position - 1] != "\\":
                name = _NAME_TAIL.match(value, position + 1).group(0)
                raise FlattenError(f"{where}: undefined parameter ${name}")
            position = value.find("$", position + 1)
        return value.replace("\\$", "$")

    def _check_files(self, tag: str, attributes: dict[str, str], where: str) -> None:
        plugin = attributes.get("type")
        # Mitsuba loads plugin `type` from `plugins/<type>.so` through the file resolver.
        if plugin is not None and not _WORD.match(plugin):
            raise FlattenError(f"{where}: plugin type {plugin!r} is not a plain name")
        if "filename" in attributes:
            attributes["filename"] = self._file(attributes["filename"], where)
        if tag == "string" and "value" in attributes:
            value = attributes["value"]
            if attributes.get("name") in FILE_PROPERTIES or self._may_name_file(value):
                attributes["value"] = self._file(value, where)

    def _may_name_file(self, value: str) -> bool:
        if not value or value == ".":
            return False
        if value.startswith(("/", "~", "\\")) or _DRIVE.match(value):
            return True
        if ".." in re.split(r"[/\\]", value):
            return True
        return os.path.lexists(self.base / value) or os.path.isfile(value)

    def _file(self, reference: str, where: str) -> str:
        """A plugin file reference: resolved against the entry scene's folder only."""
        return str(self._resolve(reference, where, [self.base]))

    def _resolve(self, reference: str, where: str, folders: list[Path]) -> Path:
        if not reference or "\x00" in reference:
            raise FlattenError(f"{where}: empty file name")
        if reference.startswith(("/", "~", "\\")) or _DRIVE.match(reference):
            raise FlattenError(f"{where}: {reference!r}: absolute paths are not allowed; name files relative to the scene")
        if "\\" in reference:
            raise FlattenError(f"{where}: {reference!r}: use '/' to separate folders")
        escapes = True
        for folder in folders:
            candidate = Path(os.path.normpath(folder / reference))
            if not _inside(candidate, self.root):
                continue  # never probe outside the root: existence there is no business of ours
            escapes = False
            if not os.path.lexists(candidate):
                continue
            real = Path(os.path.realpath(candidate))
            if not _inside(real, self.root):
                raise FlattenError(f"{where}: {reference!r} points outside the bundle")
            if not real.is_file():
                raise FlattenError(f"{where}: {reference!r} is not a file")
            self.files.append(real)
            return real
        if escapes:
            raise FlattenError(f"{where}: {reference!r} points outside the bundle")
        raise MissingFile(where, reference, Path(os.path.normpath(folders[0] / reference)))

    # -- output ---------------------------------------------------------------------------------

    def _emit(self, level: int, text: str, source: Path, line: int) -> None:
        self.chars += len(text) + 2 * level + 1
        if self.chars > MAX_DOCUMENT_CHARS:
            raise FlattenError(f"{self._label(source)}: the flattened scene exceeds {MAX_DOCUMENT_CHARS // 2**20} MiB")
        self.lines.append("  " * level + text)
        self.origins.append((self._label(source), line))


def _inside(path: Path, root: Path) -> bool:
    return path == root or path.is_relative_to(root)


def _attributes(attributes: dict[str, str]) -> str:
    # Values are final: a literal `$` is written as `\$` so Mitsuba substitutes nothing.
    return "".join(
        f' {key}="{escape(value.replace(chr(36), chr(92) + chr(36)), _ATTRIBUTE_ESCAPES)}"'
        for key, value in attributes.items()
    )


class _LineElement(Element):
    line = 0


class _LineBuilder(TreeBuilder):
    """Records each element's start line (for messages that point into the user's files)."""

    def __init__(self, label: str) -> None:
        super().__init__(element_factory=_LineElement)
        self.parser = None
        self.label = label
        self.depth = 0

    def start(self, tag, attrs):
        line = self.parser.parser.CurrentLineNumber if self.parser is not None else 0
        self.depth += 1
        if self.depth > MAX_ELEMENT_DEPTH:  # refused while reading: no deep tree is ever built
            raise FlattenError(f"{self.label}:{line}: elements nested deeper than {MAX_ELEMENT_DEPTH}")
        element = super().start(tag, attrs)
        element.line = line
        return element

    def end(self, tag):
        self.depth -= 1
        return super().end(tag)


def _parse_xml(path: Path, label: str) -> Element:
    builder = _LineBuilder(label)
    parser = DefusedXMLParser(target=builder, forbid_dtd=True)
    builder.parser = parser
    try:
        with open(path, "rb") as stream:
            while chunk := stream.read(1 << 20):
                parser.feed(chunk)
        return parser.close()
    except FlattenError:
        raise
    except defusedxml.DTDForbidden as exc:
        raise FlattenError(f"{label}: DTDs are not allowed in scene XML") from exc
    except defusedxml.EntitiesForbidden as exc:
        raise FlattenError(f"{label}: entity declarations are not allowed in scene XML") from exc
    except defusedxml.DefusedXmlException as exc:
        raise FlattenError(f"{label}: unsafe XML ({exc})") from exc
    except ParseError as exc:
        raise FlattenError(f"{label}: not well-formed XML ({exc})") from exc
    except OSError as exc:
        raise FlattenError(f"{label}: cannot read ({exc.strerror})") from exc
