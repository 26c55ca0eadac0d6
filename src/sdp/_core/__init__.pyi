from ._validate import format_bytes
