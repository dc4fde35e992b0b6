/* The types of drivers._frames defined outside _frames.c */
#ifndef DRIVERS_WIT_H
#define DRIVERS_WIT_H
#include <Python.h>
extern PyTypeObject WitStreamType; /* _wit.c */
#endif
