"""Sphinx tweaks for the flnotes book (loaded through ``sphinx.local_extensions`` in _config.yml).

MathJax on every page: Sphinx adds the MathJax script only to pages whose own body
has math, but the navigation sidebar repeats every chapter title on every page, and
a title with math (``$\\Phi$``) would show as raw ``\\(\\Phi\\)`` on pages without
math of their own. The script is the local copy from sphinx-mathjax-offline, so
this costs no network access.
"""


def setup(app):
    app.set_html_assets_policy("always")
    return {"parallel_read_safe": True, "parallel_write_safe": True}
