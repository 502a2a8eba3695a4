"""octcl."""
