"""What a zip's end record says about its central directory, read before the directory is.

`zipfile.ZipFile(...)` reads and parses the whole central directory when it opens an archive,
so an upload whose directory lists millions of entries costs that parse before any entry cap
applies. The end-of-central-directory record (the last 22 bytes, before an optional comment)
states the entry count and the directory's size; reading it first lets the caller refuse early.
`zipfile` reads exactly the stated number of directory bytes, so a cap on that size bounds its
parse even when the stated count lies.

Layout: PKWARE APPNOTE.TXT 6.3, sections 4.3.14 (zip64 end record), 4.3.15 (zip64 locator) and
4.3.16 (end record).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import BinaryIO

END_SIGNATURE = b"PK\x05\x06"
END_FORMAT = "<4s4H2LH"  # signature, disk, directory disk, entries here, entries total, size, offset, comment length
END_SIZE = struct.calcsize(END_FORMAT)  # 22
MAX_COMMENT = 0xFFFF
LOCATOR_SIGNATURE = b"PK\x06\x07"
LOCATOR_FORMAT = "<4sLQL"  # signature, disk, zip64 end record offset, disks
LOCATOR_SIZE = struct.calcsize(LOCATOR_FORMAT)  # 20
ZIP64_SIGNATURE = b"PK\x06\x06"
ZIP64_FORMAT = "<4sQ2H2L4Q"  # signature, record size, versions, disks, entries here, entries total, size, offset
ZIP64_SIZE = struct.calcsize(ZIP64_FORMAT)  # 56
# A field at its maximum means "see the zip64 record".
ZIP64_MARKERS = (0xFFFF, 0xFFFFFFFF)


@dataclass(frozen=True)
class DirectorySize:
    entries: int  # the larger of the record's two entry counts
    size: int  # bytes of the central directory


def read_directory_size(archive: BinaryIO) -> DirectorySize | None:
    """The end record's entry count and directory size, zip64 where it applies; None where no
    end record is found (the caller's zip reader then reports the archive as unreadable).
    Leaves the stream at its start."""
    try:
        archive.seek(0, 2)
        length = archive.tell()
        start = max(0, length - END_SIZE - MAX_COMMENT)
        archive.seek(start)
        tail = archive.read(length - start)
        position = tail.rfind(END_SIGNATURE)
        if position < 0 or position + END_SIZE > len(tail):
            return None
        fields = struct.unpack(END_FORMAT, tail[position:position + END_SIZE])
        entries, size = max(fields[3], fields[4]), fields[5]
        if fields[3] in ZIP64_MARKERS or fields[4] in ZIP64_MARKERS or fields[5] in ZIP64_MARKERS or fields[6] in ZIP64_MARKERS:
            zip64 = _zip64_size(archive, tail, position)
            if zip64 is not None:
                return zip64
        return DirectorySize(entries, size)
    finally:
        archive.seek(0)


def _zip64_size(archive: BinaryIO, tail: bytes, end_position: int) -> DirectorySize | None:
    locator_at = end_position - LOCATOR_SIZE
    if locator_at < 0 or tail[locator_at:locator_at + 4] != LOCATOR_SIGNATURE:
        return None
    _, _, record_offset, _ = struct.unpack(LOCATOR_FORMAT, tail[locator_at:end_position])
    archive.seek(record_offset)
    record = archive.read(ZIP64_SIZE)
    if len(record) < ZIP64_SIZE or record[:4] != ZIP64_SIGNATURE:
        return None
    fields = struct.unpack(ZIP64_FORMAT, record)
    return DirectorySize(max(fields[6], fields[7]), fields[8])
