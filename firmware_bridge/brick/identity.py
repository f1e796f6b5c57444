"""Who is running: a hash of the brick program's source and the runtime's name and version.

The host writes both into every log's provenance, so a log names the exact program that made it.
"""

import os
import sys

try:
    import uhashlib as hashlib
except ImportError:
    import hashlib


def program_hash(folder):
    """First 16 hex digits of SHA-256 over the brick modules (name and bytes, sorted by name)."""
    h = hashlib.sha256()
    for name in sorted(os.listdir(folder)):
        if name.endswith(".py"):
            h.update(name.encode())
            with open(folder + "/" + name, "rb") as fh:
                h.update(fh.read())
    return "".join("%02x" % b for b in h.digest()[:8])


def runtime():
    impl = sys.implementation
    return "%s %s" % (impl.name, ".".join(str(v) for v in impl.version[:3]))
