"""Row gathers and scatters of packed samples, as 4-byte words (any dtype whose rows are whole
words: float32, int32, int64, bfloat16 pairs ...), one thread per word so that a warp reads and
writes whole rows, contiguously (the inference renderer's index work, and the forward of a
per-sample embedding lookup); and the lookup's backward, a scatter-add of rows that come in runs
of equal indices (the samples of a ray share its image)."""

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


# grad_weight[rows[i], c] += grad_out[i, c], both row-major with C columns. Item = chunk·C + c
# sums column c over the `run` rows of its chunk, one atomic add per run of equal indices in it
# (samples of one ray share their image, so a chunk of a ray's samples adds once).
@wp.kernel
def add_rows_in_runs(first: int, grad_out: wp.array(dtype=float), rows: wp.array(dtype=wp.int64), cols: int,
                     run: int, grad_weight: wp.array(dtype=float)):
    item = first + wp.tid()
    chunk = item // cols
    col = item - chunk * cols
    start = chunk * run
    end = wp.min(start + run, rows.shape[0])
    current = rows[start]
    total = float(0.0)
    for i in range(start, end):
        row = rows[i]
        if row != current:
            wp.atomic_add(grad_weight, int(current) * cols + col, total)
            total = float(0.0)
            current = row
        total += grad_out[i * cols + col]
    wp.atomic_add(grad_weight, int(current) * cols + col, total)
