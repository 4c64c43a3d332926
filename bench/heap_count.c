/* The heap bytes a process has live at once, for `bench/torch_step.py` on the CPU: the
 * counterpart of the `osrt` binary's counting allocator (`crates/trainer/src/memory.rs`),
 * so that both sides of a CPU step report the same quantity (`peak_heap_gib`) rather than
 * osrt's heap beside PyTorch's resident pages (which include its libraries).
 *
 * Loaded with LD_PRELOAD, it replaces glibc's allocation functions with ones that forward
 * to glibc's own (`__libc_*`) and count `malloc_usable_size` of each block: PyTorch's CPU
 * tensors come from `posix_memalign`, C++'s `new` from `malloc`. Python's small-object
 * arenas are mapped directly and not counted (a few MB). The counters are read and reset
 * through ctypes: `heapcount_live`, `heapcount_peak`, `heapcount_reset_peak`.
 *
 * Build: cc -O2 -shared -fPIC -o libheapcount.so heap_count.c (torch_step.py does).
 */
#define _GNU_SOURCE
#include <errno.h>
#include <malloc.h>
#include <stddef.h>
#include <stdint.h>
#include <unistd.h>

extern void *__libc_malloc(size_t);
extern void *__libc_calloc(size_t, size_t);
extern void *__libc_realloc(void *, size_t);
extern void *__libc_memalign(size_t, size_t);
extern void __libc_free(void *);

/* Signed: a block glibc handed out before this library was loaded may be freed through
 * it, and must not wrap the count. */
static int64_t live, peak;

static void grew(void *p) {
    if (!p) return;
    int64_t now = __atomic_add_fetch(&live, (int64_t)malloc_usable_size(p), __ATOMIC_RELAXED);
    int64_t old = __atomic_load_n(&peak, __ATOMIC_RELAXED);
    while (now > old &&
           !__atomic_compare_exchange_n(&peak, &old, now, 1, __ATOMIC_RELAXED, __ATOMIC_RELAXED)) {
    }
}

static void shrank(void *p) {
    if (p) __atomic_sub_fetch(&live, (int64_t)malloc_usable_size(p), __ATOMIC_RELAXED);
}

int64_t heapcount_live(void) { return __atomic_load_n(&live, __ATOMIC_RELAXED); }
int64_t heapcount_peak(void) { return __atomic_load_n(&peak, __ATOMIC_RELAXED); }
/* The peak from now on starts at what is live now (as `memory::reset_peak_heap`). */
void heapcount_reset_peak(void) {
    __atomic_store_n(&peak, __atomic_load_n(&live, __ATOMIC_RELAXED), __ATOMIC_RELAXED);
}

void *malloc(size_t n) {
    void *p = __libc_malloc(n);
    grew(p);
    return p;
}

void *calloc(size_t k, size_t n) {
    void *p = __libc_calloc(k, n);
    grew(p);
    return p;
}

void free(void *p) {
    shrank(p);
    __libc_free(p);
}

void *realloc(void *p, size_t n) {
    size_t before = p ? malloc_usable_size(p) : 0;
    void *q = __libc_realloc(p, n);
    if (q) {
        __atomic_sub_fetch(&live, (int64_t)before, __ATOMIC_RELAXED);
        grew(q);
    } else if (p && n == 0) {
        /* realloc(p, 0) freed p. */
        __atomic_sub_fetch(&live, (int64_t)before, __ATOMIC_RELAXED);
    }
    return q;
}

void *memalign(size_t align, size_t n) {
    void *p = __libc_memalign(align, n);
    grew(p);
    return p;
}

void *aligned_alloc(size_t align, size_t n) { return memalign(align, n); }

int posix_memalign(void **out, size_t align, size_t n) {
    if (align < sizeof(void *) || (align & (align - 1)) != 0) return EINVAL;
    void *p = memalign(align, n);
    if (!p && n) return ENOMEM;
    *out = p;
    return 0;
}

void *valloc(size_t n) { return memalign((size_t)sysconf(_SC_PAGESIZE), n); }

void *pvalloc(size_t n) {
    size_t page = (size_t)sysconf(_SC_PAGESIZE);
    return memalign(page, (n + page - 1) / page * page);
}
