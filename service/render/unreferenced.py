"""Mitsuba's "unreferenced property" error, said about the user's own file and line.

Mitsuba refuses a property that the plugin it belongs to never reads — most often a misspelt
name (`<integer name="max_dpeth" value="8"/>` on a `path` integrator). It reports the line of
the *plugin's* element in the document it was given; for us that is the flattened document
(service/render/flatten.py), so the message is rewritten to point at the property's own line
in the user's file (an include's lines stay the include's), one line, naming each property.
"""
from __future__ import annotations

import re

from service.render.flatten import FlatScene

# Mitsuba 3.9, parser.cpp: 'While loading <source> (line L, col C): Found N unreferenced
# propert(y|ies) in <type> plugin of type "<plugin>":' then '- <kind> "<name>": <value>' per
# property (folded onto one line by the caller).
_FOUND = re.compile(r'\(line (\d+), col \d+\): Found \d+ unreferenced propert(?:y|ies) in (\w+) plugin of type '
                    r'"([^"]+)":(.*)')
_ITEM = re.compile(r'- \w+ "([^"]+)"')
INDENT = "  "  # the flattener writes each level of nesting two spaces deeper


def unreferenced_message(flat: FlatScene, message: str) -> str | None:
    """The one-line error for Mitsuba's unreferenced-property `message` about `flat`'s
    document, or None when the message is about something else."""
    match = _FOUND.search(message)
    if match is None:
        return None
    element_line, kind, plugin, items = int(match.group(1)), match.group(2), match.group(3), match.group(4)
    names = _ITEM.findall(items)
    if not names:
        return None
    lines = flat.document.split("\n")
    places = [flat.locate(property_line(lines, element_line, name)) for name in names]
    reason = f'in {kind} plugin of type "{plugin}", which reads no property of that name (misspelt?)'
    if len(names) == 1:
        return f'{places[0]}: unreferenced property "{names[0]}" {reason}'
    listed = ", ".join(f'"{name}" ({place})' for name, place in zip(names, places))
    return f"{places[0]}: unreferenced properties {listed} {reason}"


def property_line(lines: list[str], element_line: int, name: str) -> int:
    """The 1-based document line of the direct child `name="…"` of the element that starts
    at `element_line`; the element's own line when none is found."""
    if not 1 <= element_line <= len(lines):
        return element_line
    depth = _depth(lines[element_line - 1])
    attribute = re.compile(rf'\sname="{re.escape(name)}"')
    for index in range(element_line, len(lines)):
        line = lines[index]
        if not line.strip() or _depth(line) <= depth:
            break
        if _depth(line) == depth + 1 and attribute.search(line):
            return index + 1
    return element_line


def _depth(line: str) -> int:
    return (len(line) - len(line.lstrip(" "))) // len(INDENT)
