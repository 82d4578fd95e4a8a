"""The paper's stages, one module or package each (docs/architecture.md): track/ (Sec. 3.1),
physics/ (Sec. 3.2), appearance/ and relight (Sec. 3.3), avatar, animate, render, export,
evaluate, simulate, pose. Each has a config dataclass and ``run(inputs, out=, config=,
progress=)``; base.py holds the protocol. Import the stage modules directly; nothing is
re-exported here."""
