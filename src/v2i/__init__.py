"""v2i: cooperative V2I perception over an emulated radio link (command-line entry point)."""
