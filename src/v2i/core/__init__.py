"""The bottom layer: ObjectArray, coordinate frames and the compiled-kernel registry (imports nothing of the project)."""
