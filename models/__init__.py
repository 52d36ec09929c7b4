"""Model specifications of comest-bayes (TOML files, one per model).

This folder is the top-level ``models/`` of the repository, installed as the
package ``comest_bayes.models`` so that :func:`comest_bayes.modelspec.load_spec`
finds the files with :mod:`importlib.resources`.  It holds no Python code; the
format is documented in ``README.md`` next to this file.
"""
