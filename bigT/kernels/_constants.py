"""Constants the numba kernels and their wrappers share, importable without numba."""

# The status codes of the CSR checks (numba's check_csr_internal and numpy's check_csr).
CSR_OK = 0
CSR_BAD_INDPTR = 1
CSR_INDEX_OUT_OF_RANGE = 2
CSR_NOT_FINITE = 3

#: Rows of A multiplied together by spgemm_grouped_internal: 8 float64 lanes are one
#: cache line of the accumulator and one AVX-512 (two AVX2) fused multiply-adds.
GROUP = 8
