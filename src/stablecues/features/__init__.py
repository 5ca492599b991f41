"""Binary local features behind one :class:`Extractor` protocol."""
