"""Row gathers and scatters of packed samples, as 4-byte words (any dtype whose rows are whole
words: float32, int32, int64, bfloat16 pairs ...), one thread per word so that a warp reads and
writes whole rows, contiguously. No gradient (the inference renderer's index work)."""

import warp as wp

wp.set_module_options({"enable_backward": False})


# Item = i·words + w is word w of row i; its word in the full array is rows[i]·words + w.
@wp.func
def word_in_rows(item: int, words: int, rows: wp.array(dtype=wp.int64)) -> int:
    i = item // words
    return int(rows[i]) * words + (item - i * words)


# out[i, w] = src[rows[i], w] for the `words` 4-byte words w of a row.
@wp.kernel
def gather_words(first: int, src: wp.array(dtype=wp.int32), rows: wp.array(dtype=wp.int64), words: int,
                 out: wp.array(dtype=wp.int32)):
    item = first + wp.tid()
    out[item] = src[word_in_rows(item, words, rows)]


# dst[rows[i], w] = values[i, w] (rows distinct).
@wp.kernel
def scatter_words(first: int, values: wp.array(dtype=wp.int32), rows: wp.array(dtype=wp.int64), words: int,
                  dst: wp.array(dtype=wp.int32)):
    item = first + wp.tid()
    dst[word_in_rows(item, words, rows)] = values[item]
