"""Capture data: trials (read, write, synthesise) and motion-capture readers (Motive, Vicon,
C3D, marker sets to poses)."""
