/*
 * What every octcl kernel file shares; octcl/device/programs.py puts this file before each one
 * (then `#line 1`, so that a compiler's line numbers are the kernel file's).
 *
 *   real, real2, complex_t   float, float2, float2; or double, double2, double2 where the host
 *                            defines OCTCL_DOUBLE (a float64 build, cl_khr_fp64). real2 is a
 *                            double-word number (hi, lo) or an affine map (a, b); complex_t is
 *                            (Re, Im).
 *
 * Every other shared constant comes from the host as a -D define (octcl/device/programs.py,
 * build_options): no kernel file defines a value that the host also holds.
 */

#ifdef OCTCL_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real;
typedef double2 real2;
typedef double2 complex_t;
#else
typedef float real;
typedef float2 real2;
typedef float2 complex_t;
#endif
