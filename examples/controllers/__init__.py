"""Example controllers for ``tagswarm-agent --agent-module`` (docs/controllers.md)."""
