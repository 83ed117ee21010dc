"""The lexical rules shared by the reader and the writer (docs/device-spec.md §2)."""

from __future__ import annotations

import re

TAG = re.compile(r"[A-Za-z0-9_-]{1,8}")
#: Paths are checked fully by services.kernel.paths in the backend; the line only
#: needs them free of spaces, '=' and escapes. 256 is services.kernel.paths.MAX_PATH_LENGTH.
PATH = re.compile(r"[A-Za-z0-9_.-]{1,256}")
PARAM_NAME = re.compile(r"[A-Za-z0-9_.-]{1,64}")
ERROR_CODE = re.compile(r"[0-9]{1,3}")
VERSION = re.compile(r"[0-9]{1,4}")
