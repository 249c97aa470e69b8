"""The query page of ``openfusion web``: its HTML, JavaScript and CSS (package data, no code)."""
