"""The process runtime every tagswarm process stands on, next to the protocol: configuration
from flags and environment (:mod:`.config`), the process's life and exit codes
(:mod:`.process`), stream bookkeeping (:mod:`.streams`) and the lockstep participant
(:mod:`.lockstep`).  It imports only :mod:`tagswarm.protocol`; world, agents and server
may import it."""
