"""The `certify` command line: parser, commands, the `[tool.certify]` policy, the
display and shell completion."""
