"""``mcdenoise bench``: inference time, peak memory, FLOP use and training throughput of every
model beside Open Image Denoise, in one interleaved run (see docs/PERFORMANCE.md)."""
