"""A whole persistence study from one description: ``perscli study``.

The description (:mod:`.config`) is expanded into a graph of tasks
(:mod:`.plan`): each SCA-exposure rendered once without persistence (its
fluence is the history of later ones), each final exposure rendered again
with every persistence model and source, shapes measured with and without,
then pooled, correlated, compared with the additive-shear budget and
summarised (:mod:`.summary`).  Every task writes one FITS product into the
study folder with its provenance; :mod:`.runner` runs the graph serially or
on dask.distributed, skipping products already made, so that a killed run
resumes and any scheduler gives the same bytes.
"""
