"""The samples on disk: the sample record (``sample``: key, ``SampleMeta``, JPEG quality), the image codec
(``encode``, ``encode_pool``, ``nvjpeg``), the WebDataset shards and their index (``webdataset``) and the file
that says which benchmark a folder of shards is (``benchmark_file``).

Public names: ``SampleMeta``, ``webdataset.ShardWriter``/``iter_shard``, ``encode.encode_sample``.
"""
