/* Entry points that Debian 13's builds of lavapipe and the Khronos validation layer need and
 * Debian 12's libc, libstdc++, libxcb and libwayland lack (see tools/lavapipe_coop.sh). Each is
 * defined with the symbol version its caller asks for (shim.map). */
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>

/* C23 variants of strtol and friends (glibc 2.38): the same except that C23 also accepts a
 * 0b prefix, which neither library parses. */
long __isoc23_strtol(const char *s, char **e, int b) { return strtol(s, e, b); }
long long __isoc23_strtoll(const char *s, char **e, int b) { return strtoll(s, e, b); }
unsigned long __isoc23_strtoul(const char *s, char **e, int b) { return strtoul(s, e, b); }
unsigned long long __isoc23_strtoull(const char *s, char **e, int b) { return strtoull(s, e, b); }
int __isoc23_sscanf(const char *s, const char *f, ...) {
    va_list ap;
    va_start(ap, f);
    int r = vsscanf(s, f, ap);
    va_end(ap);
    return r;
}

/* GCC 13's iostream initialisation hook: Debian 12's libstdc++ initialises its streams when it
 * loads, so there is nothing to do. */
void _ZSt21ios_base_library_initv(void) {}

/* GCC 14: std::terminate from a noexcept region (the argument is the exception in flight). */
void _ZSt9terminatev(void) __attribute__((noreturn));
void __cxa_call_terminate(void *exception) {
    (void)exception;
    _ZSt9terminatev();
}

/* Window-system entry points newer than Debian 12's libxcb and libwayland. Lavapipe needs them
 * resolved to load; compute never calls them, and a call aborts with a message. */
static void unavailable(const char *f) {
    fprintf(stderr, "extranerf lavapipe shim: %s is not available on this system\n", f);
    abort();
}
typedef struct { unsigned int sequence; } cookie;
void *wl_display_create_queue_with_name(void *d, const char *n) {
    (void)d;
    (void)n;
    unavailable("wl_display_create_queue_with_name");
    return 0;
}
cookie xcb_present_pixmap_synced(void) { unavailable("xcb_present_pixmap_synced"); return (cookie){0}; }
cookie xcb_dri3_free_syncobj(void) { unavailable("xcb_dri3_free_syncobj"); return (cookie){0}; }
cookie xcb_dri3_import_syncobj_checked(void) { unavailable("xcb_dri3_import_syncobj_checked"); return (cookie){0}; }
