"""Limits a command checks before it loads anything heavy (no numpy here: the command
line's parser reads them at start-up)."""

DEFAULT_MAX_KNOTS = 50_000   # about 14 h of mission at one knot per second: ~2 GB, ~3 min
