"""Recording and replay: the run folder of ``tagswarm up`` (:mod:`.runrecorder`), MCAP recordings with
Foxglove views, ``tagswarm record`` and ``tagswarm replay``."""
