"""Built-in object classes: one module per class, each defining ``CLASS``, an
:class:`articulated_dataset.classes.ObjectClass` (template name, sampling table, joints):
data, importing no registry.

:data:`articulated_dataset.registry.BUILTIN_GENERATORS` lists these modules and the registry
loads them on first use; adding a class means adding ``urdf_templates/<name>.urdf.xacro``, a
module ``<name>.py`` here and its name in that list.  ``common`` holds values several tables
share; ``realistic`` the joint size distributions of ``--table realistic`` (with their
sources), which each class module turns into its ``REALISTIC_TABLE``.

Numbers are the paper's Appendix A (Tables 3 and 4) converted to SI: geometry in metres
(the paper lists cm), prismatic configuration in metres (the paper lists cm).
"""
