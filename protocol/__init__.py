"""The contract between tagswarm processes: messages, keys, codec, scenario, bus."""
