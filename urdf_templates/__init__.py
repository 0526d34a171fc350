"""Xacro templates, one ``<class>.urdf.xacro`` per object class, plus shared ``common.xacro``."""
