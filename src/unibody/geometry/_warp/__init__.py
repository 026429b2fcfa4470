"""Warp kernels, each beside the torch function it mirrors (style.md §5.6)."""
