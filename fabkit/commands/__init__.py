"""One module per command: ``run(args) -> int``. Edge code: reads the spec,
calls the pure pipeline functions, writes outputs atomically, prints."""
