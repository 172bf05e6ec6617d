"""What an operator sends to a running system: ``tagswarm goto``, ``tagswarm kidnap``."""
