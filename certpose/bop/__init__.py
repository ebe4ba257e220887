"""Whole datasets the BOP benchmark's way: conversion of the shared YCB-Video frames into the BOP
layout, pose runs over a dataset's targets (in process or on Dask, streamed and resumable), the
BOP results file, and the BOP 2019 metrics (VSD, MSSD, MSPD, average recall) with ADD(-S).

The file formats themselves are read and written by :mod:`certpose.io.bop` (metres inside,
millimetres on disk).
May import the other sub-packages of certpose (it runs the pose pipeline over a dataset) and
solvers' public names; nothing below it imports it.
"""
