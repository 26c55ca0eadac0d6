from ._memory import format_bytes, memory_limit
