"""Row gathers and scatters of packed samples, as 4-byte words (any dtype whose rows are whole
words: float32, int32, int64, bfloat16 pairs ...), one thread per word so that a warp reads and
writes whole rows, contiguously. No gradient (the inference renderer's index work)."""

import warp as wp

wp.set_module_options({"enable_backward": False})


# out[i, w] = src[rows[i], w] for the `words` 4-byte words w of a row; item = i·words + w.
@wp.kernel
def gather_words(first: int, src: wp.array(dtype=wp.int32), rows: wp.array(dtype=wp.int64), words: int,
                 out: wp.array(dtype=wp.int32)):
    item = first + wp.tid()
    i = item // words
    w = item - i * words
    out[item] = src[int(rows[i]) * words + w]


# dst[rows[i], w] = values[i, w] (rows distinct); item = i·words + w.
@wp.kernel
def scatter_words(first: int, values: wp.array(dtype=wp.int32), rows: wp.array(dtype=wp.int64), words: int,
                  dst: wp.array(dtype=wp.int32)):
    item = first + wp.tid()
    i = item // words
    w = item - i * words
    dst[int(rows[i]) * words + w] = values[item]
