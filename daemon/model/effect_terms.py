"""Terms for the effects discovery adds beyond the paper's model, registered with ``register_term``.

Imported by ``daemon.model`` so a model file naming these terms loads anywhere.
"""
