"""The formats' declarations, one small module per family: each defines ``FORMATS`` (extension ->
:class:`~splatdeform.io.format.Format`) with its header probe, ``info`` fields and source
conversion; ``splatdeform.io`` merges them into its one table. Importing a declaration imports
no reader: its functions import the format's module when called."""
