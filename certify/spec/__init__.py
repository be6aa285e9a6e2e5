"""System specs: the whitelist parser, expressions, the definedness check, `System`,
the enclosures of f and h over boxes, and the built-in specs."""
