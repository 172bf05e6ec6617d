"""Deployment on several hosts or containers: ``tagswarm router`` with its ACL and secrets,
``tagswarm alive`` healthchecks."""
