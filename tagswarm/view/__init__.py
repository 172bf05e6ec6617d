"""``tagswarm view`` (the live web page; its files in ``web/``) and ``tagswarm snapshot``."""
