"""motok.data"""
