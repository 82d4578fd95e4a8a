"""The paper's stages, one file each (DESIGN.md): track.py is Sec. 3.1 (mesh tracking),
physics.py Sec. 3.2. Import the stage modules directly; nothing is re-exported here."""
