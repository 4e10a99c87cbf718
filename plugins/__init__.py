"""Swappable components: one module per plugin under encoder/, head/ and model/, each with a YAML in conf/."""
