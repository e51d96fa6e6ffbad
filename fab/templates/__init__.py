"""The HTML pages of the fabrication stages, rendered from jinja2 templates.

``base.html`` holds what every page shares (the document head and the one
stylesheet, ``style.css``, set inline so that a page stays readable when its
folder is moved or mailed alone); each page extends it:

- ``fab_report.html``: the fabrication report (``fab.package.report``)
- ``verify_report.html``: the verification report (``fab.verify.report``)
- ``run_index.html``: the run folder's front page (``fab.run.summary``)

Autoescaping is on: every value a page shows is text, never markup.
"""

import functools

STYLESHEET = "style.css"


@functools.cache
def _environment():
    import jinja2

    return jinja2.Environment(
        loader=jinja2.PackageLoader("fab", "templates"),
        autoescape=True,
        undefined=jinja2.StrictUndefined,  # a value the page names but was not given
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=True,
    )


def render_page(template, **values):
    """Return the page ``template`` (a file name in this folder) filled with ``values``.

    Parameters
    ----------
    template : str
        Template file name, such as ``"fab_report.html"``.
    **values
        The names the template uses.

    Returns
    -------
    str
        The HTML page, ending in a newline.
    """
    return _environment().get_template(template).render(**values)
