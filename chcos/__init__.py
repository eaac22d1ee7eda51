"""chcos - the Concurrent Hierarchical Control operating system (CHC-OS) for robot cells."""
