/* Preloaded before libfaketime into a service whose wall clock a test sets wrong (tests/support/skewed_clock.py).
 *
 * libfaketime 0.9.10 (Debian bookworm) with FAKETIME_DONT_FAKE_MONOTONIC=1 still rewrites the absolute
 * deadline of clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, ...) as if it were a faked time, and the
 * kernel refuses the result (EINVAL): Python 3.11's time.sleep fails (libfaketime issue #426). The
 * monotonic clock is not faked here, so its sleeps go to the kernel untouched; every other clock's go on
 * to libfaketime. */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

int clock_nanosleep(clockid_t clock_id, int flags, const struct timespec *req, struct timespec *rem)
{
    if (clock_id == CLOCK_MONOTONIC)
        return syscall(SYS_clock_nanosleep, clock_id, flags, req, rem) == 0 ? 0 : errno;
    static int (*next)(clockid_t, int, const struct timespec *, struct timespec *);
    if (next == NULL)
        next = (int (*)(clockid_t, int, const struct timespec *, struct timespec *))dlsym(RTLD_NEXT, "clock_nanosleep");
    return next(clock_id, flags, req, rem);
}
