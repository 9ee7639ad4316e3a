"""The commands users run (`python tools/<name>.py ...`), importable as `tools.<name>` from the
repository root, so tests call a tool's `main(argv)` in-process. Not installed with detbench."""
