"""``tagswarm spy``: a live table of the keys, types, rates and bandwidth of a running system."""
