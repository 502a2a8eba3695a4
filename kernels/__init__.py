"""OpenCL kernel sources of octcl, one operation per file."""
