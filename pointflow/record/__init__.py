"""Recording the stream to MCAP (docs/record.md): config, the recorder stage, the
PointCloud2 encoder, split files, and ``pointflow inspect``."""
