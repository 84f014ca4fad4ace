"""Images: correction maps and remapping, stacks, the USAF target, edge analysis."""
