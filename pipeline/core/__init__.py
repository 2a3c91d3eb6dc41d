"""The core every stage stands on: errors, geometry, atomic I/O and caches, where outputs live, the
manifest, the split table's schema, the robot, the input protocol. Imports nothing else of skidbench."""
