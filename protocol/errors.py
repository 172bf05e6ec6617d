"""The root of every error tagswarm raises on purpose, as Gymnasium's ``error.py``.

Each module keeps its own error class, a subclass of one of these two::

    TagswarmError                       anything tagswarm raises on purpose
    ├── UsageError                      bad input from whoever started the process: exit code 2
    │   ├── ConfigError                 flags and environment (tagswarm.runtime.config)
    │   ├── ScenarioError               a scenario or an override of it (protocol.scenario_schema)
    │   ├── KeyNameError                a run id, role or camera name unfit for a key (protocol.keys)
    │   ├── BusError                    Zenoh settings, or a session that cannot open (protocol.bus)
    │   ├── JournalError                a journal of another map, or in use (server.journal)
    │   ├── RunFolderError              a missing or malformed run folder (tagswarm.evaluation.runfolder)
    │   └── RecordingError              not a readable MCAP recording (tagswarm.recording.mcapio)
    ├── DecodeError                     a payload rejected at the edge: dropped and counted (protocol.codec)
    ├── PlacementError                  a robot that cannot be put where asked (world.sim)
    ├── CheckpointError                 a fusion snapshot that does not decode (server.checkpoint)
    └── Rejected                        a pose estimate the agent drops, with the reason (agents.cubegeom)

:func:`tagswarm.runtime.process.run_main` is the one boundary: a :class:`UsageError`
becomes one line on stderr and exit code 2.  The others are handled where they arise
(counted, logged, refused) and reach it only as bugs.  Classes that were ``ValueError``
before this root existed still are one, so existing ``except ValueError`` keeps working.
"""

from __future__ import annotations


class TagswarmError(Exception):
    """Root of every error tagswarm raises on purpose."""


class UsageError(TagswarmError):
    """Bad input from whoever started the process (flags, environment, scenario, files it
    names); the message is one line naming what to fix, and the process exits with code 2."""
